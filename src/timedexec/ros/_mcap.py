"""The node's log, and the log as MCAP with ROS 2 encodings (no rclpy needed).

The node's log is a cycle log (:func:`timedexec.monitoring.load_cycle_log` reads it, so
``timedexec monitor`` runs on it) with what the node published besides: ``sample_s`` (n,),
the host time each package was measured at (the ``header.stamp`` of its ``/joint_states``),
and in ``meta`` the offset from the host clock to the ROS clock (``ros_offset_ns``), the
joint names and every ``/diagnostics`` array the node published.

:func:`log_to_mcap` writes it as MCAP (the ``ros2`` profile, CDR-encoded messages with
their ``.msg`` definitions: Foxglove, PlotJuggler and ``ros2 bag`` open it):

* ``/joint_states`` (``sensor_msgs/msg/JointState``): each package as measured, stamped
  with its measurement instant on the ROS clock (coasted rows, which repeat a package,
  are left out);
* ``/timedexec/commands`` (``sensor_msgs/msg/JointState``): each command as sent, its
  speeds in ``velocity`` (rad/s), stamped with the instant it left;
* ``/diagnostics`` (``diagnostic_msgs/msg/DiagnosticArray``): the predicted delays, the
  cycle lock's state, refusals and the monitor's alerts, as published.

Each message's log time is its stamp.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from timedexec.errors import ConfigError, RecordingError
from timedexec.monitoring import LOG_FORMAT, load_cycle_log

__all__ = [
    "COMMAND_TOPIC",
    "MESSAGE_DEFINITIONS",
    "load_node_log",
    "log_to_mcap",
    "save_node_log",
    "stamp_ns",
]

#: Topic of the commands as sent, in the MCAP file.
COMMAND_TOPIC = "/timedexec/commands"

_SEP = "=" * 80
_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
#: The ROS 2 ``.msg`` definitions of the messages written, comments stripped, their
#: dependencies appended as rosbag2 writes them (tests/test_ros_mcap.py compares them
#: with the installed packages' files where those are installed).
MESSAGE_DEFINITIONS: dict[str, str] = {
    "sensor_msgs/msg/JointState": (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
        f"float64[] effort\n{_SEP}\nMSG: std_msgs/Header\n{_HEADER}{_SEP}\n"
        f"MSG: builtin_interfaces/Time\n{_TIME}"
    ),
    "diagnostic_msgs/msg/DiagnosticArray": (
        "std_msgs/Header header\nDiagnosticStatus[] status\n"
        f"{_SEP}\nMSG: std_msgs/Header\n{_HEADER}{_SEP}\nMSG: builtin_interfaces/Time\n{_TIME}"
        f"{_SEP}\nMSG: diagnostic_msgs/DiagnosticStatus\nbyte OK=0\nbyte WARN=1\nbyte ERROR=2\n"
        "byte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\n"
        f"KeyValue[] values\n{_SEP}\nMSG: diagnostic_msgs/KeyValue\nstring key\nstring value\n"
    ),
}

_NODE_LOG_VERSION = 1


def stamp_ns(host_s: float, ros_offset_ns: int) -> int:
    """ROS time (ns) of host time ``host_s`` (s), given the offset ROS minus host, ns."""
    return round(host_s * 1e9) + int(ros_offset_ns)


def _time(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def save_node_log(
    path: str | os.PathLike[str],
    arrays: Mapping[str, NDArray[Any]],
    *,
    sample_s: NDArray[np.float64],
    period_s: float,
    robot: str,
    joint_names: Sequence[str],
    ros_offset_ns: int,
    diagnostics: Sequence[Mapping[str, Any]] = (),
) -> Path:
    """Write the node's log (see the module's docstring) as .npz, whole or not at all.

    Parameters
    ----------
    arrays : dict
        :meth:`CycleLog.arrays` of the run (n rows).
    sample_s : ndarray (n,)
        Host time each row's package was measured at, s.
    period_s : float
        Controller period, s.
    robot : str
        Robot name.
    joint_names : 6 str
        The names the node published.
    ros_offset_ns : int
        ROS clock minus host clock, ns.
    diagnostics : sequence of dict
        The ``/diagnostics`` arrays published, each ``{"stamp_ns": int, "status": [...]}``
        with status dicts of ``level``, ``name``, ``message``, ``hardware_id``, ``values``
        (a dict of str).
    """
    from timedexec._files import write_atomic

    n = len(arrays["arrival_s"])
    sample = np.asarray(sample_s, dtype=float)
    if sample.shape != (n,):
        raise ConfigError(f"sample_s has shape {sample.shape}; give one time per row ({n},)")
    meta = {
        "format": LOG_FORMAT,
        "format_version": 1,
        "period_s": float(period_s),
        "robot": robot,
        "node_log_version": _NODE_LOG_VERSION,
        "joint_names": list(joint_names),
        "ros_offset_ns": int(ros_offset_ns),
        "diagnostics": list(diagnostics),
    }
    columns: dict[str, Any] = {k: np.asarray(v) for k, v in arrays.items()}
    columns.update(meta=np.array(json.dumps(meta)), sample_s=sample)
    buf = io.BytesIO()
    np.savez_compressed(buf, **columns)
    return write_atomic(path, buf.getvalue())


def load_node_log(path: str | os.PathLike[str]) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
    """Read a log written by :func:`save_node_log`: ``(arrays, meta)``.

    Raises
    ------
    RecordingError
        Not a cycle log, or a cycle log without what the node adds (``sample_s``,
        ``ros_offset_ns``, ``joint_names``).
    """
    arrays, meta = load_cycle_log(path)
    if meta.get("node_log_version") != _NODE_LOG_VERSION or "sample_s" not in arrays:
        raise RecordingError(
            f"{os.fspath(path)}: a cycle log without the node's stamps (sample_s, "
            "ros_offset_ns); write it with `timedexec ros --log PATH`"
        )
    return arrays, meta


def log_to_mcap(log_path: str | os.PathLike[str], mcap_path: str | os.PathLike[str]) -> Path:
    """Convert the node's log (:func:`save_node_log`) to MCAP (see the module's docstring).

    Returns
    -------
    Path
        ``mcap_path``, written whole (a temporary file renamed into place).

    Raises
    ------
    RecordingError
        ``log_path`` is not the node's log.
    ConfigError
        ``mcap`` and ``mcap-ros2-support`` are not installed (``pip install 'timedexec[ros]'``).
    """
    try:
        from mcap_ros2.writer import Writer
    except ImportError as exc:
        raise ConfigError(
            "writing MCAP needs the mcap and mcap-ros2-support packages: "
            "pip install 'timedexec[ros]'"
        ) from exc
    from timedexec._files import write_atomic

    arrays, meta = load_node_log(log_path)
    names = list(meta["joint_names"])
    offset = int(meta["ros_offset_ns"])
    buf = io.BytesIO()
    writer = Writer(buf)
    js = writer.register_msgdef("sensor_msgs/msg/JointState", MESSAGE_DEFINITIONS["sensor_msgs/msg/JointState"])
    diag = writer.register_msgdef("diagnostic_msgs/msg/DiagnosticArray", MESSAGE_DEFINITIONS["diagnostic_msgs/msg/DiagnosticArray"])  # fmt: skip
    coasted = np.asarray(arrays.get("coasted", np.zeros(len(arrays["arrival_s"]), bool)))
    for i in range(len(arrays["arrival_s"])):
        if coasted[i]:
            continue
        ns = stamp_ns(float(arrays["sample_s"][i]), offset)
        message = {
            "header": {"stamp": _time(ns), "frame_id": ""},
            "name": names,
            "position": [float(x) for x in arrays["q"][i]],
            "velocity": [],
            "effort": [],
        }
        writer.write_message("/joint_states", js, message, log_time=ns, sequence=int(arrays["sequence"][i]))  # fmt: skip
    for k in np.flatnonzero(np.isfinite(arrays["send_s"])):
        ns = stamp_ns(float(arrays["send_s"][k]), offset)
        message = {
            "header": {"stamp": _time(ns), "frame_id": ""},
            "name": names,
            "position": [],
            "velocity": [float(x) for x in arrays["qd_cmd"][k]],
            "effort": [],
        }
        writer.write_message(COMMAND_TOPIC, js, message, log_time=ns)
    for d in meta.get("diagnostics", []):
        ns = int(d["stamp_ns"])
        message = {
            "header": {"stamp": _time(ns), "frame_id": ""},
            "status": [
                {
                    "level": int(s["level"]),
                    "name": str(s["name"]),
                    "message": str(s["message"]),
                    "hardware_id": str(s.get("hardware_id", "")),
                    "values": [{"key": k, "value": str(v)} for k, v in s["values"].items()],
                }
                for s in d["status"]
            ],
        }
        writer.write_message("/diagnostics", diag, message, log_time=ns)
    writer.add_metadata(
        "timedexec", {"robot": str(meta["robot"]), "period_s": repr(meta["period_s"]), "ros_offset_ns": str(offset)}
    )  # fmt: skip
    writer.finish()  # type: ignore[no-untyped-call]
    return write_atomic(mcap_path, buf.getvalue())
