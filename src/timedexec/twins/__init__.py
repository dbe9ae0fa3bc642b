"""timedexec.twins: protocol servers that real clients talk to, and their ground truth.

* :class:`URTwin` — a simulated UR controller (RTDE on 30004, dashboard on 29999, script
  port 30003) that the real ``ur_rtde`` client connects to;
* :class:`RSITwin` — a simulated KUKA controller speaking RSI XML over UDP;
* :class:`GyroTwin` — a simulated MPU-6000 streaming frames over a pseudo-terminal;
* the truth files they write (:func:`read_twin_truth`, one reader) and the truth of a live
  calibration run against a twin (:func:`twin_truth_table`, :func:`compare_with_truth`);
* the RTDE codec the UR twin speaks (:class:`RTDERecipe`, :class:`RTDEPackageType`,
  :data:`RTDE_OUTPUT_TYPES`, :data:`RTDE_INPUT_TYPES`, :func:`encode_rtde_package`,
  :func:`decode_rtde_header`), for a peer of the twin written without ``ur_rtde``.

Every twin is a :class:`Twin`: one lifecycle (``start``, ``stop``, ``kill``, ``stall``,
``drop``) and a context manager. Each runs the simulated controller of :mod:`timedexec.sim`
in its own process or thread; nothing here is needed to use a real robot.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from timedexec.twins._lifecycle import Twin
from timedexec.twins._truth import (
    GyroClockTruth,
    TruthComparison,
    TwinTruth,
    compare_with_truth,
    envelope_transport_latency,
    gyro_window_start_s,
    iter_truth_records,
    measure_gyro_transport_latency,
    read_twin_truth,
    twin_truth_table,
)

if TYPE_CHECKING:
    from timedexec.twins._gyro import GyroTwin
    from timedexec.twins._rsi import (
        STOP_REASONS,
        RSITwin,
        RSITwinConfig,
        RSITwinStatus,
        free_udp_port,
        read_rsi_truth,
    )
    from timedexec.twins._rsi_gyro import publish_controller_origin, rsi_gyro_factory
    from timedexec.twins._rtde import (
        RTDE_HEADER_SIZE,
        RTDE_INPUT_TYPES,
        RTDE_OUTPUT_TYPES,
        RTDE_TYPE_CODES,
        RTDEPackageType,
        RTDERecipe,
        decode_rtde_header,
        enable_receive_stamps,
        encode_rtde_package,
        recv_stamped,
    )
    from timedexec.twins._ur import (
        DASHBOARD_PORT,
        DEFAULT_PHYSICS_RATE_HZ,
        RTDE_PORT,
        SCRIPT_PORT,
        UR_CONTROLLER_VERSIONS,
        URTwin,
        read_truth,
        run_ur_twin,
    )
    from timedexec.twins._urprograms import (
        EXTERNAL_CONTROL_PORT,
        EXTERNAL_CONTROL_URP,
        fetch_external_control_script,
    )

# The servers load on first use: they pull in sockets, multiprocessing and pty code.
_LAZY = {
    "GyroTwin": "timedexec.twins._gyro",
    "STOP_REASONS": "timedexec.twins._rsi",
    "RSITwin": "timedexec.twins._rsi",
    "RSITwinConfig": "timedexec.twins._rsi",
    "RSITwinStatus": "timedexec.twins._rsi",
    "free_udp_port": "timedexec.twins._rsi",
    "read_rsi_truth": "timedexec.twins._rsi",
    "publish_controller_origin": "timedexec.twins._rsi_gyro",
    "rsi_gyro_factory": "timedexec.twins._rsi_gyro",
    "RTDE_HEADER_SIZE": "timedexec.twins._rtde",
    "RTDE_INPUT_TYPES": "timedexec.twins._rtde",
    "RTDE_OUTPUT_TYPES": "timedexec.twins._rtde",
    "RTDE_TYPE_CODES": "timedexec.twins._rtde",
    "RTDEPackageType": "timedexec.twins._rtde",
    "RTDERecipe": "timedexec.twins._rtde",
    "decode_rtde_header": "timedexec.twins._rtde",
    "encode_rtde_package": "timedexec.twins._rtde",
    "enable_receive_stamps": "timedexec.twins._rtde",
    "recv_stamped": "timedexec.twins._rtde",
    "DASHBOARD_PORT": "timedexec.twins._ur",
    "DEFAULT_PHYSICS_RATE_HZ": "timedexec.twins._ur",
    "RTDE_PORT": "timedexec.twins._ur",
    "SCRIPT_PORT": "timedexec.twins._ur",
    "UR_CONTROLLER_VERSIONS": "timedexec.twins._ur",
    "URTwin": "timedexec.twins._ur",
    "read_truth": "timedexec.twins._ur",
    "run_ur_twin": "timedexec.twins._ur",
    "EXTERNAL_CONTROL_PORT": "timedexec.twins._urprograms",
    "EXTERNAL_CONTROL_URP": "timedexec.twins._urprograms",
    "fetch_external_control_script": "timedexec.twins._urprograms",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'timedexec.twins' has no attribute {name!r}")


__all__ = [
    "DASHBOARD_PORT",
    "DEFAULT_PHYSICS_RATE_HZ",
    "EXTERNAL_CONTROL_PORT",
    "EXTERNAL_CONTROL_URP",
    "RTDE_HEADER_SIZE",
    "RTDE_INPUT_TYPES",
    "RTDE_OUTPUT_TYPES",
    "RTDE_PORT",
    "RTDE_TYPE_CODES",
    "SCRIPT_PORT",
    "STOP_REASONS",
    "UR_CONTROLLER_VERSIONS",
    "GyroClockTruth",
    "GyroTwin",
    "RSITwin",
    "RSITwinConfig",
    "RSITwinStatus",
    "RTDEPackageType",
    "RTDERecipe",
    "TruthComparison",
    "Twin",
    "TwinTruth",
    "URTwin",
    "compare_with_truth",
    "decode_rtde_header",
    "enable_receive_stamps",
    "encode_rtde_package",
    "envelope_transport_latency",
    "fetch_external_control_script",
    "free_udp_port",
    "gyro_window_start_s",
    "iter_truth_records",
    "measure_gyro_transport_latency",
    "publish_controller_origin",
    "read_rsi_truth",
    "read_truth",
    "read_twin_truth",
    "recv_stamped",
    "rsi_gyro_factory",
    "run_ur_twin",
    "twin_truth_table",
]
