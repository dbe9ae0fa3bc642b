"""The node's log and its MCAP form (timedexec.ros; mcap and mcap-ros2-support, no rclpy)."""

from __future__ import annotations

import math
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap_ros2", reason="MCAP needs mcap-ros2-support: pip install '.[ros]'")

with warnings.catch_warnings():  # the reader imports a deprecated mcap_ros1 module
    warnings.simplefilter("ignore", DeprecationWarning)
    from mcap_ros2.reader import read_ros2_messages

from timedexec.errors import ConfigError, RecordingError
from timedexec.monitoring import load_cycle_log, save_cycle_log
from timedexec.robots import get_robot_entry
from timedexec.ros import (
    COMMAND_TOPIC,
    MESSAGE_DEFINITIONS,
    load_node_log,
    log_to_mcap,
    ros_environment,
    save_node_log,
    stamp_ns,
)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

NAMES = get_robot_entry("ur10").joint_names
OFFSET_NS = 1_795_000_000_000_000_000  # a ROS (system) time minus a host monotonic time


def cycle_log(n: int = 50, seed: int = 0) -> dict[str, np.ndarray]:
    """A cycle log of ``n`` packages at 8 ms, a command on every other one, one coasted row."""
    rng = np.random.default_rng(seed)
    arrival = 100.0 + 0.008 * np.arange(n) + rng.uniform(0, 1e-3, n)
    send = np.where(np.arange(n) % 2 == 0, arrival + 3e-4, np.nan)
    qd_cmd = np.where(np.isfinite(send)[:, None], rng.normal(0, 0.1, (n, 6)), np.nan)
    coasted = np.zeros(n, bool)
    coasted[7] = True
    return {
        "arrival_s": arrival, "controller_s": 0.008 * np.arange(n), "sequence": np.arange(n),
        "send_s": send, "target_s": np.full(n, np.nan), "clipped": np.zeros(n, bool),
        "coasted": coasted, "qd_cmd": qd_cmd, "q": rng.normal(0, 1, (n, 6)),
        "target_qd": np.full((n, 6), np.nan),
    }  # fmt: skip


DIAGNOSTICS = [
    {"stamp_ns": OFFSET_NS + 100_200_000_000, "status": [
        {"level": 0, "name": "timedexec: predicted delays", "message": "m", "hardware_id": "ur10",
         "values": {"shoulder_pan_joint actuation_s": "0.019"}},
        {"level": 2, "name": "timedexec: trajectory", "message": "refused: start time too soon",
         "hardware_id": "ur10", "values": {}},
    ]},
]  # fmt: skip


def write_log(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    sample = arrays["arrival_s"] - 0.0041
    return save_node_log(
        path, arrays, sample_s=sample, period_s=0.008, robot="ur10", joint_names=NAMES,
        ros_offset_ns=OFFSET_NS, diagnostics=DIAGNOSTICS,
    )  # fmt: skip


def test_the_node_log_is_a_cycle_log_the_monitor_reads(tmp_path: Path) -> None:
    """``timedexec monitor`` (load_cycle_log) reads the node's log; load_node_log gives the
    stamps, the offset, the names and the diagnostics back unchanged."""
    arrays = cycle_log()
    path = write_log(tmp_path / "log.npz", arrays)
    plain, meta = load_cycle_log(path)
    np.testing.assert_array_equal(plain["q"], arrays["q"])
    got, meta = load_node_log(path)
    np.testing.assert_array_equal(got["sample_s"], arrays["arrival_s"] - 0.0041)
    assert meta["ros_offset_ns"] == OFFSET_NS
    assert tuple(meta["joint_names"]) == NAMES
    assert meta["diagnostics"] == DIAGNOSTICS


def test_a_plain_cycle_log_is_not_a_node_log(tmp_path: Path) -> None:
    """A cycle log without the node's stamps is refused, saying how to get one."""
    path = save_cycle_log(tmp_path / "plain.npz", cycle_log(), period_s=0.008, robot="ur10")
    with pytest.raises(RecordingError, match="timedexec ros --log"):
        load_node_log(path)


def test_mcap_reads_back_equal_to_the_log(tmp_path: Path) -> None:
    """Read with the mcap ROS 2 reader, the MCAP holds every package but the coasted one on
    /joint_states (positions and stamps exactly), every command with its speeds and send
    time, and the diagnostics as published (levels, names, values)."""
    arrays = cycle_log()
    log = write_log(tmp_path / "log.npz", arrays)
    mcap = log_to_mcap(log, tmp_path / "run.mcap")
    msgs = list(read_ros2_messages(str(mcap)))
    js = [m for m in msgs if m.channel.topic == "/joint_states"]
    rows = np.flatnonzero(~arrays["coasted"])
    assert len(js) == len(rows) == 49
    for m, i in zip(js, rows, strict=True):
        ns = stamp_ns(arrays["arrival_s"][i] - 0.0041, OFFSET_NS)
        assert m.ros_msg.header.stamp.sec * 10**9 + m.ros_msg.header.stamp.nanosec == ns
        assert m.log_time_ns == ns
        assert list(m.ros_msg.position) == arrays["q"][i].tolist()
        assert list(m.ros_msg.name) == list(NAMES)
    cmd = [m for m in msgs if m.channel.topic == COMMAND_TOPIC]
    sent = np.flatnonzero(np.isfinite(arrays["send_s"]))
    assert len(cmd) == len(sent) == 25
    for m, i in zip(cmd, sent, strict=True):
        assert m.log_time_ns == stamp_ns(arrays["send_s"][i], OFFSET_NS)
        assert list(m.ros_msg.velocity) == arrays["qd_cmd"][i].tolist()
    (diag,) = [m for m in msgs if m.channel.topic == "/diagnostics"]
    assert diag.log_time_ns == DIAGNOSTICS[0]["stamp_ns"]
    assert [s.level for s in diag.ros_msg.status] == [0, 2]
    assert diag.ros_msg.status[0].values[0].key == "shoulder_pan_joint actuation_s"
    assert diag.ros_msg.status[1].message == "refused: start time too soon"


def test_message_definitions_are_the_installed_ones() -> None:
    """The definitions written into the MCAP schemas are the installed packages' .msg files
    with comments stripped (where the ROS message packages are installed)."""
    # The wheels install share/ under the environment's prefix; a sourced ROS installation
    # names its prefixes in AMENT_PREFIX_PATH.
    prefixes = [Path(sys.prefix), *map(Path, filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)))]  # fmt: skip

    def msg(pkg_type: str) -> str:
        pkg, name = pkg_type.split("/")
        files = [p / "share" / pkg / "msg" / f"{name}.msg" for p in prefixes]
        found = [f for f in files if f.is_file()]
        if not found:
            pytest.skip(f"{pkg_type}.msg is not installed (pip install '.[ros]')")
        text = found[0].read_text()
        lines = (line.split("#", 1)[0].rstrip() for line in text.splitlines())
        return "".join(f"{line}\n" for line in lines if line)

    for full, text in MESSAGE_DEFINITIONS.items():
        parts = text.split("=" * 80 + "\n")
        assert parts[0] == msg(full.replace("/msg/", "/")), full
        for part in parts[1:]:
            head, body = part.split("\n", 1)
            assert head.startswith("MSG: ")
            assert body == msg(head[5:]), head


def test_ros_environment_sets_what_rclpy_reads() -> None:
    """Fast DDS by default (a choice already made is kept), the domain id in range, and
    localhost-only discovery through the Jazzy-and-later variable."""
    env: dict[str, str] = {"ROS_LOCALHOST_ONLY": "1"}
    ros_environment(env, domain_id=42, localhost_only=True)
    assert env == {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp", "ROS_DOMAIN_ID": "42",
                   "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}  # fmt: skip
    env = {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    ros_environment(env)
    assert env == {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    with pytest.raises(ConfigError, match=r"0 \.\. 232"):
        ros_environment({}, domain_id=233)
    assert math.isfinite(stamp_ns(1.5, 0))
