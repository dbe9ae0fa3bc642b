"""A ROS 2 client of the ``timedexec`` node, run as its own process by tests/test_ros_twin.py.

It does what a ROS user's program does and nothing of timedexec: it listens to
``/joint_states`` (noting each message's receipt on its ROS clock), then sends joint
trajectories stamped ``--lead`` seconds ahead on ``/timedexec/joint_trajectory`` and
collects ``/diagnostics``. Each trajectory moves one joint by ``--distance`` rad on a
speed trapezoid (0.4 rad/s, ramps of 8 rad/s², the calibration sweep's), sampled every
10 ms into points with positions and velocities (which joint_trajectory_controller joins
with cubics: exact for this profile, whose kinks fall on the points). It prints one JSON
object on stdout.

Usage: python tests/test_ros_client.py --listen 2 --moves 1:+1,2:-1,3:+1 --lead 1.5
(ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE come from the environment).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

SPEED_RAD_S = 0.4
ACCEL_RAD_S2 = 8.0
STEP_S = 0.01


def trapezoid(distance_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (s), displacements (rad) and speeds (rad/s) of the move's points."""
    ramp = SPEED_RAD_S / ACCEL_RAD_S2  # 50 ms
    d = abs(distance_rad)
    cruise = (d - SPEED_RAD_S * ramp) / SPEED_RAD_S
    total = 2 * ramp + cruise
    t = np.round(np.arange(0.0, total + 1e-9, STEP_S), 9)
    if t[-1] < total - 1e-9:
        t = np.append(t, total)
    v = np.minimum.reduce([ACCEL_RAD_S2 * t, np.full_like(t, SPEED_RAD_S), ACCEL_RAD_S2 * (total - t)])
    v = np.maximum(v, 0.0)
    x = np.empty_like(t)
    for i, ti in enumerate(t):
        if ti <= ramp:
            x[i] = 0.5 * ACCEL_RAD_S2 * ti**2
        elif ti <= ramp + cruise:
            x[i] = 0.5 * SPEED_RAD_S * ramp + SPEED_RAD_S * (ti - ramp)
        else:
            r = total - ti
            x[i] = d - 0.5 * ACCEL_RAD_S2 * r**2
    s = np.sign(distance_rad)
    return t, s * x, s * v


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", type=float, default=2.0, help="s of /joint_states to record")
    ap.add_argument("--moves", default="", help="joint:sign,... (1-based joints)")
    ap.add_argument("--distance", type=float, default=0.2)
    ap.add_argument("--lead", type=float, default=1.5)
    ap.add_argument("--extra", default="", help="also send: 'soon' (a stamp 1 ms ahead), 'zero' (stamp 0)")
    args = ap.parse_args()

    import rclpy
    from builtin_interfaces.msg import Duration
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    rclpy.init()
    node = rclpy.create_node("timedexec_test_client")
    clock = node.get_clock()
    states: list[tuple[int, int, list[str], list[float]]] = []
    diags: list[dict] = []

    def on_state(msg: JointState) -> None:
        states.append((clock.now().nanoseconds, msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec, list(msg.name), list(msg.position)))  # fmt: skip

    def on_diag(msg: DiagnosticArray) -> None:
        diags.append({s.name: {"level": s.level[0] if isinstance(s.level, bytes) else int(s.level), "message": s.message, "values": {kv.key: kv.value for kv in s.values}} for s in msg.status})  # fmt: skip

    node.create_subscription(JointState, "/joint_states", on_state, 100)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    pub = node.create_publisher(JointTrajectory, "/timedexec/joint_trajectory", 10)
    ex = SingleThreadedExecutor()
    ex.add_node(node)

    def spin_for(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)

    # Wait for the node (its first state), then record.
    deadline = time.monotonic() + 30.0
    while not states and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    if not states:
        print(json.dumps({"error": "no /joint_states within 30 s"}))
        return 1
    first = len(states)
    spin_for(args.listen)
    listen = states[first:]
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline + 30:
        spin_for(0.05)

    def send(joint: int, sign: float, lead_s: float | None) -> dict:
        names = states[-1][2]
        q0 = np.array(states[-1][3])
        t, x, v = trapezoid(sign * args.distance)
        msg = JointTrajectory()
        msg.joint_names = names
        for ti, xi, vi in zip(t, x, v, strict=True):
            p = JointTrajectoryPoint()
            q = q0.copy()
            q[joint - 1] += xi
            qd = np.zeros(6)
            qd[joint - 1] = vi
            p.positions = q.tolist()
            p.velocities = qd.tolist()
            sec = int(ti)
            p.time_from_start = Duration(sec=sec, nanosec=round((ti - sec) * 1e9))
            msg.points.append(p)
        sent_ns = clock.now().nanoseconds
        stamp = 0 if lead_s is None else sent_ns + round(lead_s * 1e9)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        pub.publish(msg)
        return {"joint": joint, "stamp_ns": stamp, "sent_ns": sent_ns, "target": (q0 + np.eye(6)[joint - 1] * x[-1]).tolist(),
                "times_s": t.tolist(), "x_rad": x.tolist(), "v_rad_s": v.tolist()}  # fmt: skip

    sent = []
    for move in filter(None, args.moves.split(",")):
        j, s = move.split(":")
        info = send(int(j), float(s), args.lead)
        spin_for(args.lead + info["times_s"][-1] + 0.5)
        info["final_q"] = states[-1][3]
        sent.append(info)
    if "soon" in args.extra:
        n_diag = len(diags)
        sent.append(send(1, 1.0, 0.001) | {"soon": True})
        spin_for(1.0)
        sent[-1]["diagnostics"] = diags[n_diag:]
        sent[-1]["final_q"] = states[-1][3]
    if "zero" in args.extra:  # a zero stamp: as soon as the node can
        n_diag = len(diags)
        sent.append(send(1, -1.0, None) | {"zero": True})
        spin_for(args.distance / SPEED_RAD_S + 1.0)
        sent[-1]["diagnostics"] = diags[n_diag:]
        sent[-1]["final_q"] = states[-1][3]
    json.dump({"listen": listen, "sent": sent, "diagnostics": diags[-3:]}, sys.stdout)
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
