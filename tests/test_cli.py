"""The ``timedexec`` command line as a whole: every subcommand wired to its library call,
the documented exit codes, the one ``--json [PATH]`` convention, and a quick ``--help``.

The library calls are replaced by small fakes (monkeypatched on the package's public face,
which the commands import when they run), so these tests check the command layer alone;
the commands' real work is tested in test_cli_simulate, test_learning_cli, ... .
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from timedexec.cli import main
from timedexec.errors import (
    ConfigError,
    DriverError,
    DriverTimeout,
    ModelError,
    ProtocolError,
    RecordingError,
    SensorError,
    StaleStateError,
    TimedExecError,
)
from timedexec.robots import ROBOT_NAMES


class Call:
    """Stand-in for a library function: records each call, then returns or raises."""

    def __init__(self, result: Any = None) -> None:
        self.result = result
        self.raises: BaseException | None = None
        self.calls: list[tuple[tuple[Any, ...], dict[str, Any]]] = []

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls.append((args, kwargs))
        if self.raises is not None:
            raise self.raises
        return self.result


class FakeDriver:
    """A robot driver that is only opened and closed (the runner is a fake too)."""

    controller_period_s = 0.008  # the simulated UR10's, which `calibrate` plans for

    def __enter__(self) -> FakeDriver:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def gyro(self, seed: int) -> str:
        return f"virtual gyro {seed}"


class FakeTable:
    """A delay table of 12 trials: enough for `train` to print its banner."""

    def __len__(self) -> int:
        return 12

    def __contains__(self, name: object) -> bool:
        return False

    def to_csv(self, path: str) -> None:
        Path(path).write_text("trial\n", encoding="utf-8")

    @classmethod
    def read_csv(cls, path: Path) -> FakeTable:
        return cls()


class FakeModel:
    robot = "ur10"
    period_s = 0.008
    manifest: dict[str, Any] = {"arrays": {"bytes": 2000}}  # noqa: RUF012

    def save(self, out: Path) -> None:
        out.mkdir(parents=True, exist_ok=True)


SIM_SUMMARY = {"recording": "s.h5", "trials": 3, "simulated_now": 3, "recording_bytes": 1e6,
               "truth": None}  # fmt: skip
CAL_SUMMARY = {"recording": "c.h5", "planned": 2, "recorded_now": 2}
EXTRACT_SUMMARY = {"trials": 12, "flagged": 0, "filter_cutoff_hz": 100.0,
                   "gyro_rate_error_ppm": 12.0}  # fmt: skip
CV = {"actuation_delay": {"median": {"1": 3.0, "combined": 3.1, "average": 3.0}}}
EVALUATION = {"robot": "ur10", "strategies": {"none": {"timing_rms_ms": 20.0}},
              "coverage_95": 0.95}  # fmt: skip
DISCREPANCY = {"added_effects": ["gravity_load"], "unexplained": []}
FLEET = {"summary": {"robots": 1, "ok": 1, "failed": []}, "robots": []}
MONITOR = {"verdict": "ok", "threshold": 9.27, "arl0_moves": 10000, "warmup_moves": 100,
           "alerts": [],
           "joints": [{"joint": 1, "status": "ok", "moves": 120, "gap_to_model_ms": -1.1,
                       "shift_ms": 0.05}]}  # fmt: skip
_JOINT = {"median_ms": 20.0, "p2_5_ms": 15.0, "p97_5_ms": 25.0}
DEMO = {
    "summary": {"joints": {"1": {"actuation_delay": _JOINT, "response_delay": _JOINT}},
                "flagged": 0},
    "extraction_rmse_ms": {"actuation_delay": 0.1, "response_delay": 0.2},
    "folds": 2,
    "cv_ms": {"actuation_delay": {"median": 3.0}},
    "noise_floor_ms": {"actuation_delay": 2.0},
    "evaluation": {"strategies": {"none": {"timing_rms_ms": 20.0, "seam_error_cm": 1.0}},
                   "coverage_95": 0.95},
    "conveyor": {"compensated": {"mean_lag_cm": 0.1, "final_lag_cm": 0.0,
                                 "actuation_shift_ms": 20.0}},
    "report": "demo/report/report.md", "model": "demo/model", "delays": "demo/delays.csv",
}  # fmt: skip


@pytest.fixture
def fakes(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> dict[str, Call]:
    """Every library entry point the commands call, replaced by a :class:`Call`; the
    working folder is ``tmp_path`` so relative outputs land there."""
    # Import every patched module's importers first: a module imported while a fake is in
    # place (execution imports drivers.open_driver by name) would keep the fake afterwards.
    import timedexec.evaluation
    import timedexec.report  # noqa: F401

    monkeypatch.chdir(tmp_path)
    extraction = SimpleNamespace(table=FakeTable(), summary=lambda: dict(EXTRACT_SUMMARY))
    training = SimpleNamespace(
        model=FakeModel(),
        cv=SimpleNamespace(to_dict=lambda: CV, table_text=lambda: "Table I: actuation delay"),
        seconds=1.5,
    )
    discrepancy = SimpleNamespace(
        summary_text=lambda: "discrepancy of ur10: gravity_load added",
        warnings=["few repeats"],
        to_dict=lambda: DISCREPANCY,
        write_report=lambda d: Path(d) / "report.md",
    )
    evaluation = SimpleNamespace(to_dict=lambda: EVALUATION, table=lambda: "none  20.00 ms")
    calls = {
        "timedexec.sim.simulate_sweep": Call(SimpleNamespace(summary=lambda: SIM_SUMMARY)),
        "timedexec.twins.run_ur_twin": Call(),
        "timedexec.drivers.open_driver": Call(FakeDriver()),
        "timedexec.calibration.run_calibration": Call(SimpleNamespace(summary=lambda: CAL_SUMMARY)),
        "timedexec.extraction.extract_recording": Call(extraction),
        "timedexec.extraction.check_recording": Call([]),
        "timedexec.sensors.check_gyro": Call(
            SimpleNamespace(
                ok=True,
                to_dict=lambda: {"ok": True, "problems": []},
                summary=lambda: "/dev/ttyACM0: meets what calibration needs",
            )
        ),
        "timedexec.learning.train_delay_models": Call(training),
        "timedexec.evaluation.evaluate": Call(evaluation),
        "timedexec.discrepancy.analyse_discrepancy": Call(discrepancy),
        "timedexec.fleet.run_fleet": Call(
            SimpleNamespace(failed=(), document=FLEET, summary_text=lambda: "fleet of 1 robots")
        ),
        "timedexec.monitoring.moves_from_recording": Call(
            ([], {"robot": "ur10", "period_s": 0.008})
        ),
        "timedexec.monitoring.DelayMonitor": Call(
            SimpleNamespace(update=lambda moves: None, summary=lambda: dict(MONITOR))
        ),
        "timedexec.ros.run_node": Call(0),
        "timedexec.report.build_report": Call(Path("r") / "report.md"),
        "timedexec.report.run_demo": Call(DEMO),
    }
    for target, call in calls.items():
        monkeypatch.setattr(target, call)
    monkeypatch.setattr("timedexec.delays.DelayTable", FakeTable)
    monkeypatch.setattr(signal, "signal", Call())  # `serve` must not take over SIGTERM here
    (tmp_path / "d.csv").write_text("trial\n", encoding="utf-8")
    (tmp_path / "r.h5").write_bytes(b"")  # monitor checks its input is a file
    (tmp_path / "m.csv").write_text("name,robot,source\na,ur10,a.h5\n", encoding="utf-8")
    return {target.rpartition(".")[2]: call for target, call in calls.items()}


# command: (argv, the library call, the keyword arguments it must receive, a line of its text)
COMMANDS: dict[str, tuple[list[str], str, dict[str, Any], str]] = {
    "simulate": (["simulate", "--robot", "UR10", "--trials", "3", "--seed", "7", "--out",
                  "s.h5", "--jobs", "2", "--quiet"], "simulate_sweep",
                 {"seed": 7, "jobs": 2, "progress": False, "resume": False},
                 "recorded 3 trials of ur10 to s.h5 (1.0 MB)"),
    "serve": (["serve", "--robot", "ur10", "--seed", "4"], "run_ur_twin",
              {"seed": 4, "truth_path": None, "imu_link": None,
               "external_control": ("127.0.0.1", 50002)}, ""),
    "gyro": (["gyro", "check", "/dev/ttyACM0", "--duration-s", "2", "--full-scale-dps", "1000"],
             "check_gyro", {"duration_s": 2.0, "full_scale_dps": 1000, "sensor": "mpu6000"},
             "/dev/ttyACM0: meets what calibration needs"),
    "calibrate": (["calibrate", "--robot-url", "sim://ur10", "--trials", "2", "--seed", "3",
                   "--out", "c.h5", "--quiet", "--no-tracking-phases"], "run_calibration",
                  {"resume": False, "progress": False, "source": "sim://ur10"},
                  "recorded 2 trials (2 planned) to c.h5"),
    "check": (["check", "r.h5"], "check_recording", {"deep": True},
              "r.h5: a valid timedexec recording"),
    "extract": (["extract", "r.h5", "--out", "d2.csv", "--method", "extrema", "--quiet"],
                "extract_recording", {"method": "extrema", "jobs": 1, "progress": False},
                "extracted 12 trials (0 flagged) with method extrema to d2.csv"),
    "train": (["train", "d.csv", "--out", "bundle", "--folds", "2", "--methods", "median",
               "--quiet"], "train_delay_models", {"folds": 2, "methods": ("median",),
                                                  "random_state": 0, "time_input": False},
              "bundle for ur10 at 8 ms written to bundle (2 kB arrays) in 1.5 s"),
    "evaluate": (["evaluate", "--robot", "ur10", "--configs", "5", "--quiet"], "evaluate",
                 {"n_configs": 5, "seed": 20261, "draws": 20, "speed_m_s": 0.5},
                 "none  20.00 ms"),
    "discrepancy": (["discrepancy", "d.csv", "--start", "base", "--report", "rep", "--quiet"],
                    "analyse_discrepancy", {"start": "base", "robot": None, "alpha": 0.01},
                    "discrepancy of ur10: gravity_load added"),
    "fleet": (["fleet", "m.csv", "--out", "fleet", "--scheduler", "", "--quiet"], "run_fleet",
              {"scheduler": None, "jobs": 1, "progress": False}, "fleet of 1 robots"),
    "monitor": (["monitor", "r.h5", "--model", "ur10-sim", "--warmup", "50"], "DelayMonitor",
                {"warmup_moves": 50, "arl0_moves": 10000.0}, "no alarm"),
    # ros: the node prints nothing on stdout (it publishes; status on stderr)
    "ros": (["ros", "--robot-url", "sim://ur10", "--model", "ur10-sim"], "run_node", {}, ""),
    "report": (["report", "d.csv", "r.h5", "--out", "r", "--trial", "3"], "build_report",
               {"trial": 3}, "report written to r/report.md"),
    "demo": (["demo", "--robot", "kr5", "--trials", "160", "--out", "demo"], "run_demo",
             {"trials": 160, "seed": 0, "eval_configs": None},
             "conveyor at 0.5 m/s, physical torch-to-seam lag"),
}  # fmt: skip

#: The JSON document each command with --json delivers (a key it must hold).
JSON_KEYS = {
    "simulate": "recording_bytes",
    "calibrate": "recorded_now",
    "check": "valid",
    "extract": "filter_cutoff_hz",
    "train": "actuation_delay",
    "evaluate": "strategies",
    "discrepancy": "added_effects",
    "fleet": "robots",
    "monitor": "alerts",
    "demo": "conveyor",
}


def help_text(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    assert main([*argv, "--help"]) == 0
    return capsys.readouterr().out


def listed_commands(text: str) -> list[str]:
    """The subcommand names of the top-level help's COMMAND section."""
    section = text.split("COMMAND\n", 1)[1].split("\n\n", 1)[0]
    return re.findall(r"^ {4}(\w+)", section, flags=re.MULTILINE)


def test_every_command_in_help_has_its_own_help(capsys: pytest.CaptureFixture[str]) -> None:
    """`timedexec --help` lists the commands in workflow order, and each of them
    answers `--help` with its own usage and exit code 0."""
    names = listed_commands(help_text(capsys))
    assert names == list(COMMANDS)
    for name in names:
        assert help_text(capsys, name).startswith(f"usage: timedexec {name} ")


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_calls_the_library_with_its_options(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str], name: str
) -> None:
    """Each subcommand parses its options, calls its library function once with them
    (robot names case-insensitive) and prints its text result on stdout, exit 0."""
    argv, target, kwargs, line = COMMANDS[name]
    assert main(argv) == 0
    call = fakes[target]
    assert len(call.calls) == 1
    got = call.calls[0][1]
    assert {k: got[k] for k in kwargs} == kwargs
    out = capsys.readouterr().out
    assert line in out


def test_help_epilog_documents_json_and_every_exit_code(capsys: pytest.CaptureFixture[str]) -> None:
    """The top-level help states the --json convention and each exit code of the map."""
    text = help_text(capsys)
    assert "--json [PATH]" in text
    assert "instead of the text" in text
    for code, what in (("0", "success"), ("1", "any other failure"), ("2", "bad input"),
                       ("3", "robot, sensor or network fault"), ("130", "interrupted"),
                       ("141", "stdout closed")):  # fmt: skip
        assert re.search(rf"^  {code} +{what}", text, flags=re.MULTILINE), code


def test_json_option_is_on_exactly_the_documented_commands(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The commands the epilog names for --json are the ones that take `--json [PATH]`,
    all with the same optional-value spelling."""
    top = help_text(capsys)
    documented = re.search(r"--json \[PATH\] \(([^)]*)\)", top)
    assert documented is not None
    named = {n.strip() for n in documented.group(1).split(",")}
    having = {n for n in COMMANDS if "[--json [PATH]]" in help_text(capsys, n)}
    assert named == having == set(JSON_KEYS)


@pytest.mark.parametrize("name", list(JSON_KEYS))
@pytest.mark.parametrize("spelling", [["--json"], ["--json", "-"], ["--json=-"]])
def test_json_on_stdout_replaces_the_text(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str], name: str, spelling: list[str]
) -> None:
    """A bare --json, `--json -` and `--json=-` print only the JSON result on stdout (it
    parses as one document), for every command that has --json."""
    argv = COMMANDS[name][0]
    assert main([*argv, *spelling]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert JSON_KEYS[name] in doc


@pytest.mark.parametrize("name", ["simulate", "train", "evaluate", "discrepancy"])
def test_json_path_writes_the_file_and_keeps_the_text(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str], tmp_path: Path, name: str
) -> None:
    """`--json PATH` writes the same JSON result to PATH and still prints the text, with a
    line naming the file."""
    argv, _, _, line = COMMANDS[name]
    assert main([*argv, "--json", "result.json"]) == 0
    out = capsys.readouterr().out
    assert line in out
    assert "wrote the JSON result to result.json" in out
    assert JSON_KEYS[name] in json.loads((tmp_path / "result.json").read_text())


def test_json_path_in_a_missing_folder_is_refused_before_any_work(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str]
) -> None:
    """A --json PATH whose folder does not exist: exit 2, the folder named, and the
    (long) library call never made."""
    argv = COMMANDS["evaluate"][0]
    assert main([*argv, "--json", "no/such/dir/e.json"]) == 2
    assert "--json no/such/dir/e.json: the folder no/such/dir does not exist" in (
        capsys.readouterr().err
    )
    assert fakes["evaluate"].calls == []


@pytest.mark.parametrize(
    ("error", "code"),
    [
        (ConfigError("--trials 0: must be >= 1"), 2),
        (RecordingError("cannot write x.h5: directory no does not exist"), 2),
        (ModelError("bundle is for 'kr5'"), 2),
        (ProtocolError("RSI frame is empty"), 2),
        (FileNotFoundError(2, "No such file or directory", "x.csv"), 2),
        (PermissionError(13, "Permission denied", "x.csv"), 2),
        (DriverError("robot stopped: protective stop"), 3),
        (DriverTimeout("ur://10.0.0.9: no state package within 1 s"), 3),
        (StaleStateError("state is 40 ms old"), 3),
        (SensorError("cannot open gyro port '/dev/ttyUSB0'"), 3),
        (ConnectionResetError(104, "Connection reset by peer"), 3),
        (BrokenPipeError(32, "Broken pipe"), 3),  # a socket, not stdout: a network fault
        (TimeoutError(), 3),
        (TimedExecError("something else went wrong"), 1),
    ],
    ids=lambda v: type(v).__name__ if isinstance(v, BaseException) else str(v),
)
def test_error_classes_map_to_the_documented_exit_codes(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str], error: BaseException, code: int
) -> None:
    """Bad input (timedexec's input errors, a missing or unreadable file) exits 2; a robot,
    sensor or network fault exits 3 even though DriverTimeout and SensorError are OSErrors;
    any other TimedExecError exits 1. Always one line on stderr, never a traceback."""
    fakes["build_report"].raises = error
    assert main(COMMANDS["report"][0]) == code
    err = capsys.readouterr().err
    assert err.startswith("timedexec report: error: ")
    assert err.count("\n") == 1
    assert "Traceback" not in err


def test_driver_timeout_inside_calibrate_is_a_fault_not_bad_input(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot that stops answering mid-sweep (DriverTimeout, a TimeoutError and so an
    OSError) exits 3 with the driver's message, not 2 as for bad input."""
    fakes["run_calibration"].raises = DriverTimeout("sim://ur10: no state package within 0.5 s")
    assert main(COMMANDS["calibrate"][0]) == 3
    err = capsys.readouterr().err
    assert err == "timedexec calibrate: error: sim://ur10: no state package within 0.5 s\n"


def test_config_error_from_a_real_command_exits_2(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str]
) -> None:
    """A ConfigError raised by the command itself (an effect outside the vocabulary) exits 2
    with its message, before the library is called."""
    argv = ["simulate", "--robot", "ur10", "--trials", "4", "--effects", "friction", "--out", "x.h5"]
    assert main(argv) == 2
    assert "the vocabulary is" in capsys.readouterr().err
    assert fakes["simulate_sweep"].calls == []


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["simulate", "--robot", "ur5", "--trials", "1", "--out", "x.h5"],
         f"argument --robot: unknown robot 'ur5'; choose one of {', '.join(ROBOT_NAMES)}"),
        (["evaluate", "--robot", "ur10", "--configs", "many"], "invalid int value: 'many'"),
        (["frobnicate"], "invalid choice: 'frobnicate'"),
        ([], "usage: timedexec"),
    ],
)  # fmt: skip
def test_usage_errors_exit_2(
    capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    """argparse's errors (an unknown robot, a malformed number, an unknown command, no
    command at all) return exit code 2 from main() with the usage on stderr."""
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_ctrl_c_exits_130_with_one_line(
    fakes: dict[str, Call], capsys: pytest.CaptureFixture[str]
) -> None:
    """KeyboardInterrupt inside a command: exit 130 and the single line "interrupted" on
    stderr, no traceback."""
    fakes["extract_recording"].raises = KeyboardInterrupt()
    assert main(COMMANDS["extract"][0]) == 130
    captured = capsys.readouterr()
    assert captured.err == "timedexec extract: interrupted\n"
    assert captured.out == ""


class ClosedStdout:
    """stdout whose reader has gone: every write and flush raises BrokenPipeError."""

    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self) -> None:
        raise BrokenPipeError(32, "Broken pipe")


def test_closed_stdout_exits_quietly_in_process(
    fakes: dict[str, Call], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A BrokenPipeError on stdout while printing the result: exit 141 and nothing on
    stderr (the command's work is done; the reader just stopped listening)."""
    monkeypatch.setattr(sys, "stdout", ClosedStdout())
    assert main(COMMANDS["report"][0]) == 141
    assert capsys.readouterr().err == ""
    assert len(fakes["build_report"].calls) == 1


#: A child that runs `timedexec report` with the report builder faked (no figures drawn).
_FAKE_REPORT = (
    "import sys, timedexec.report as r\n"
    "r.build_report = lambda *a, **k: 'r/report.md'\n"
    "from timedexec.cli import main\n"
    "sys.exit(main(['report', 'x.csv', '--out', 'r']))\n"
)


@pytest.mark.parametrize(
    ("argv", "unbuffered"),
    [
        (["-m", "timedexec", "--help"], False),
        (["-c", _FAKE_REPORT], False),
        (["-c", _FAKE_REPORT], True),
    ],
    ids=["help-buffered", "result-buffered", "result-unbuffered"],
)
def test_closed_pipe_exits_141_without_a_traceback(argv: list[str], unbuffered: bool) -> None:
    """`timedexec ... | head` where the reader is gone before the output: exit 141 and an
    empty stderr, no traceback and no "Exception ignored" from the interpreter's final
    flush, whether the failed write is the result itself (unbuffered stdout) or the final
    flush of buffered output (the help). Also proves `python -m timedexec`."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if unbuffered:
        env["PYTHONUNBUFFERED"] = "1"
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run(
            [sys.executable, *argv],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            timeout=60,
            check=False,
        )
    finally:
        os.close(write_end)
    assert (proc.returncode, proc.stderr) == (141, "")


def test_other_exceptions_are_bugs_and_keep_their_traceback(fakes: dict[str, Call]) -> None:
    """An exception outside the map (a bug, not a user's problem) propagates from main()
    so its traceback reaches the report."""
    fakes["build_report"].raises = ZeroDivisionError("bug")
    with pytest.raises(ZeroDivisionError):
        main(COMMANDS["report"][0])


@pytest.mark.parametrize("module", ["timedexec", "timedexec.cli"])
def test_python_dash_m_runs_the_command(module: str) -> None:
    """`python -m timedexec` and `python -m timedexec.cli` run the same command line."""
    proc = subprocess.run(
        [sys.executable, "-m", module, "--version"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0
    assert proc.stdout.startswith("timedexec ")


def test_help_imports_no_heavy_library() -> None:
    """Building the parser and printing every command's help loads none of the heavy
    libraries (they load inside the commands), so `timedexec --help` stays fast."""
    code = (
        "import sys, contextlib, io\n"
        "from timedexec.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    for c in ('', 'simulate', 'calibrate', 'train', 'report', 'demo'):\n"
        "        main([c, '--help'] if c else ['--help'])\n"
        "heavy = ('scipy', 'h5py', 'matplotlib', 'sklearn', 'joblib', 'serial', 'rtde_control')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert proc.stdout.strip() == "[]"
