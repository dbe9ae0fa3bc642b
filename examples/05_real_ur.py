"""Calibrate a real UR robot — or, without one, the UR twin — through ur_rtde and a gyro.

With ``TIMEDEXEC_UR_HOST`` and ``TIMEDEXEC_IMU`` set (e.g. 192.168.1.10 and /dev/ttyUSB0)
this runs a few calibration trials on that robot; the robot must be in remote control, the
gyro on the flange, and the workspace clear (each trial moves one joint by 0.04 rad).
Without them it starts the simulated UR controller (a separate process speaking RTDE,
dashboard and script upload on 127.0.0.2) with a simulated gyro on a pseudo-terminal, and
the real ur_rtde client talks to that. Runs headless.

    python examples/05_real_ur.py [--trials 6]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np

from timedexec.calibration import run_calibration
from timedexec.drivers import open_driver
from timedexec.extraction import extract_recording
from timedexec.recording import SweepPlan, SweepProtocol
from timedexec.sensors import open_gyro
from timedexec.twins import URTwin


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=6)
    args = ap.parse_args()
    host = os.environ.get("TIMEDEXEC_UR_HOST")
    imu = os.environ.get("TIMEDEXEC_IMU")
    tmp = Path(tempfile.mkdtemp(prefix="timedexec-05-"))
    with contextlib.ExitStack() as stack:
        if not host:
            host, imu = "127.0.0.2", str(tmp / "gyro")
            stack.enter_context(URTwin("ur10", host, imu_link=imu, seed=5))
            print(f"no TIMEDEXEC_UR_HOST: using the simulated UR10 on {host}, gyro on {imu}")
        elif not imu:
            raise SystemExit("set TIMEDEXEC_IMU to the gyro's serial port (e.g. /dev/ttyUSB0)")
        # The robot's default protocol (from its spec); a real sensor states its measured
        # constants: SweepProtocol.for_robot("ur10", gyro=GyroHeader.from_json("gyro.json")).
        protocol = SweepProtocol.for_robot("ur10")
        plan = SweepPlan.generate("ur10", args.trials, seed=2)
        rec = tmp / "ur10.h5"
        driver = stack.enter_context(open_driver(f"ur://{host}"))
        gyro = stack.enter_context(open_gyro(imu))
        run_calibration(driver, gyro, plan, rec, protocol=protocol, progress=False,
                        source=f"ur://{host}")  # fmt: skip
    table = extract_recording(rec, progress=False).table
    act = table["actuation_delay"] * 1e3
    resp = table["response_delay"] * 1e3
    print(f"{len(table)} trials, {sum(1 for f in table['flag'] if f)} flagged")
    print(f"actuation delay: median {np.nanmedian(act):.1f} ms; response delay: median {np.nanmedian(resp):.1f} ms")
    print(f"recording: {rec}")


if __name__ == "__main__":
    main()
