"""Calibrate the simulated UR10 through the live runner, extract its delays, compare.

The same code path as a real robot: a RobotDriver (here ``sim://ur10``, the in-process
simulator in virtual time with a virtual gyro on the flange), the live trial runner writing
a resumable recording, and the extraction. Prints the delays per trial against the
simulator's ground truth. Runs headless in a few seconds.

    python examples/01_calibrate_simulated_ur10.py [--trials 16] [--out DIR]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from timedexec.calibration import run_calibration
from timedexec.drivers import open_driver
from timedexec.extraction import extract_recording
from timedexec.recording import SweepPlan, SweepProtocol


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=16)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    out_dir = args.out or Path(tempfile.mkdtemp(prefix="timedexec-01-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = out_dir / "ur10-live-sim.h5"
    if rec.exists():
        rec.unlink()
    protocol = SweepProtocol.for_robot("ur10")  # from the robot's spec, as on a real robot
    plan = SweepPlan.generate("ur10", args.trials, seed=1)
    with open_driver("sim://ur10", seed=1) as driver:
        run_calibration(driver, driver.gyro(seed=1), plan, rec, protocol=protocol, progress=False)
    table = extract_recording(rec, progress=False).table
    print("trial joint dir   actuation (ms)  truth (ms)   response (ms)  truth (ms)")
    for i in range(len(table)):
        print(
            f"{table['trial'][i]:>5} {table['joint'][i]:>5} {table['direction'][i]:>+3d} "
            f"{table['actuation_delay'][i] * 1e3:>15.2f} {table['true_actuation_delay'][i] * 1e3:>11.2f} "
            f"{table['response_delay'][i] * 1e3:>15.2f} {table['true_response_delay'][i] * 1e3:>11.2f}"
        )
    err = (table["actuation_delay"] - table["true_actuation_delay"]) * 1e3
    print(f"actuation error against ground truth: RMS {np.sqrt(np.nanmean(err**2)):.3f} ms")
    print(f"recording: {rec}")


if __name__ == "__main__":
    main()
