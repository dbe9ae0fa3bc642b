"""Fingerprint what the pipeline produces, so a refactor can show it changed nothing.

Runs a fixed, seeded set of jobs through the public API and the CLI (simulated sweeps on
every built-in robot, extraction, training, bundle arrays, a timed execution's cycle log,
the onset and conveyor evaluations, the discrepancy workflow) and prints one sha256 per
output. Run it before and after a change and diff the two listings:

    python3 scripts/fingerprint.py > before.txt
    ...change...
    python3 scripts/fingerprint.py > after.txt && diff before.txt after.txt

Numbers are hashed as the bytes of float64 arrays (what the files hold); JSON results are
hashed with keys sorted and timing fields (wall-clock seconds, versions, paths) removed, as
those change from run to run whatever the code does. About 2-3 minutes on one core.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

# Fields of JSON results that change from run to run whatever the code does.
_VOLATILE = {"elapsed_s", "wall_s", "seconds", "version", "package_version", "created",
             "recording", "truth", "out", "path", "model", "report", "recording_bytes",
             "runtime_s", "measured", "time_s", "eta_s", "duration_s", "cpu_s"}


def _strip(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _strip(v) for k, v in sorted(value.items()) if k not in _VOLATILE}
    if isinstance(value, list):
        return [_strip(v) for v in value]
    return value


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def _h5(path: Path) -> str:
    import h5py

    h = hashlib.sha256()

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            h.update(name.encode())
            h.update(np.ascontiguousarray(obj[()]).tobytes())
        for key in sorted(obj.attrs):
            if key in _VOLATILE or key.endswith("_version"):
                continue
            h.update(f"{name}@{key}={obj.attrs[key]!r}".encode())

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return h.hexdigest()[:16]


def _npz(path: Path) -> str:
    h = hashlib.sha256()
    with np.load(path, allow_pickle=False) as z:
        for key in sorted(z.files):
            h.update(key.encode())
            h.update(np.ascontiguousarray(z[key]).tobytes())
    return h.hexdigest()[:16]


def _json(path: Path) -> str:
    return _sha(json.dumps(_strip(json.loads(path.read_text())), sort_keys=True).encode())


def _cli(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "timedexec", *args, "--quiet"] if args[0] not in
                   ("discrepancy",) else [sys.executable, "-m", "timedexec", *args],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _execution_log(robot: str) -> str:
    from timedexec.drivers import open_driver
    from timedexec.execution import TimedExecutor

    spec_home = {"ur10": [0.3, -1.2, 1.4, -1.6, -1.6, 0.0],
                 "ur10e": [0.3, -1.2, 1.4, -1.6, -1.6, 0.0],
                 "kr5": [0.2, -1.4, 1.6, 0.1, 0.4, 0.0]}[robot]
    with TimedExecutor(open_driver(f"sim://{robot}?seed=3"), f"{robot}-sim") as ex:
        plan = ex.plan(spec_home)
        ex.execute(plan, start_time_s=ex.now() + 0.3)
        arrays = ex.log.arrays()
    h = hashlib.sha256()
    for key in sorted(arrays):
        value = arrays[key]
        try:
            h.update(key.encode() + np.asarray(value, dtype=float).tobytes())
        except (TypeError, ValueError):
            h.update(key.encode() + repr(value).encode())
    return h.hexdigest()[:16]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="ur10,ur10e,kr5")
    parser.add_argument("--trials", type=int, default=240)
    args = parser.parse_args(argv)
    out: dict[str, str] = {}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for robot in args.robots.split(","):
            rec, truth = tmp / f"{robot}.h5", tmp / f"{robot}-truth.csv"
            _cli("simulate", "--robot", robot, "--trials", str(args.trials), "--seed", "7",
                 "--out", str(rec), "--truth", str(truth))
            out[f"{robot} recording"] = _h5(rec)
            out[f"{robot} truth.csv"] = _sha(truth.read_bytes())
            table = tmp / f"{robot}-delays.csv"
            _cli("extract", str(rec), "--out", str(table))
            out[f"{robot} delays.csv"] = _sha(table.read_bytes())
            bundle = tmp / f"{robot}-model"
            _cli("train", str(table), "--out", str(bundle), "--folds", "3",
                 "--json", str(tmp / f"{robot}-cv.json"))
            out[f"{robot} bundle arrays"] = _npz(bundle / "arrays.npz")
            out[f"{robot} cv.json"] = _json(tmp / f"{robot}-cv.json")
            out[f"{robot} execution log"] = _execution_log(robot)
            ev = tmp / f"{robot}-eval.json"
            _cli("evaluate", "--robot", robot, "--configs", "20", "--draws", "4",
                 "--json", str(ev))
            out[f"{robot} evaluate onset"] = _json(ev)
            if robot != "ur10e":
                weld = tmp / f"{robot}-weld.json"
                _cli("evaluate", "--task", "conveyor", "--robot", robot, "--runs", "1",
                     "--cells", "1", "--json", str(weld))
                out[f"{robot} evaluate conveyor"] = _json(weld)
        disc = tmp / "disc.json"
        first = args.robots.split(",")[0]
        _cli("discrepancy", str(tmp / f"{first}-truth.csv"), "--start", "base",
             "--json", str(disc), "--quiet")
        out["discrepancy"] = _json(disc)
    for key, value in out.items():
        print(f"{key:28s} {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
