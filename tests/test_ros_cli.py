"""``timedexec ros`` at the command line: what it says without rclpy, with bad options, and
when the robot goes away (that last one with rclpy and the UR twin: slow)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from timedexec.cli import main

HOST = "127.0.0.62"


def test_without_rclpy_it_exits_2_naming_the_extra(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """With rclpy missing (an import of it fails) the command exits 2 before touching the
    robot, its one-line error naming ``pip install 'timedexec[ros]'``."""
    monkeypatch.setitem(sys.modules, "rclpy", None)  # makes `import rclpy` raise ImportError
    code = main(["ros", "--robot-url", "ur://127.0.0.250", "--model", "ur10-sim"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "pip install 'timedexec[ros]'" in err
    assert err.count("\n") == 1


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--domain-id", "233"], "from 0 to 232"),
        (["--diagnostics-period", "0"], "out of range"),
        (["--joint-names", "a,b,c"], "six distinct names"),
    ],
)
def test_bad_options_exit_2(argv: list[str], words: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Out-of-range options are refused at the command line (exit 2), saying the range."""
    code = main(["ros", "--robot-url", "ur://127.0.0.250", "--model", "ur10-sim", *argv])
    assert code == 2
    assert words in capsys.readouterr().err


def test_settings_file_must_be_executor_settings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--settings takes a JSON object of ExecutorSettings fields; an unknown field is bad
    input (exit 2) named in the message."""
    bad = tmp_path / "s.json"
    bad.write_text('{"cycle_lokc": true}')
    code = main(["ros", "--robot-url", "ur://127.0.0.250", "--model", "ur10-sim", "--settings", str(bad)])
    assert code == 2
    assert "cycle_lokc" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.ros
def test_a_lost_robot_stops_the_node_with_exit_3(tmp_path: Path) -> None:
    """The twin killed under a running node: the node logs one clear line (the robot's URL
    and what happened) and exits 3 within seconds."""
    pytest.importorskip("rclpy", reason="the ROS 2 node needs rclpy: pip install '.[ros]'")
    pytest.importorskip("rtde_control")
    from timedexec.ros import ros_environment
    from timedexec.twins import URTwin

    env = dict(os.environ)
    ros_environment(env, domain_id=100 + (os.getpid() + 50) % 100, localhost_only=True)
    env["ROS_LOG_DIR"] = str(tmp_path / "roslog")
    with URTwin("ur10", HOST, seed=5) as twin:
        node = subprocess.Popen(
            [sys.executable, "-m", "timedexec", "ros", "--robot-url", f"ur://{HOST}",
             "--model", "ur10-sim", "--localhost-only"],
            env=env, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            assert node.stderr is not None
            line = node.stderr.readline()  # the node's ready line
            assert "ur10 at ur://" in line, line
            time.sleep(0.5)
            twin.kill()
            t_kill = time.monotonic()
            _, err = node.communicate(timeout=30)
            took = time.monotonic() - t_kill
        finally:
            if node.poll() is None:
                node.send_signal(signal.SIGKILL)
    assert node.returncode == 3, err
    assert f"lost the robot at ur://{HOST}" in err
    # ur_rtde notices a dead controller by its own timeouts (seconds); 15 s bounds it.
    assert took < 15.0, took
