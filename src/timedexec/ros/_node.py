"""The ``timedexec`` ROS 2 node: a :class:`~timedexec.execution.TimedExecutor` in front of
any driver, speaking joint_trajectory_controller's topics with timing that holds.

The executor's loop runs in the calling thread, once per state package (the controller's
clock); rclpy's executor spins in a second thread and only queues what arrives. Per
package the node publishes ``joint_states`` stamped with the instant the state was
measured (its arrival back-dated by the predicted response delay in force,
:meth:`TimedExecutor.estimate`'s ``response_delay_s``, on the ROS clock). A
``JointTrajectory`` on ``~/joint_trajectory`` is interpolated as joint_trajectory_controller
does (:func:`plan_from_points`) and executed so that the arm is physically at point k at
``header.stamp + time_from_start_k`` (a zero stamp: as soon as the slowest joint's shifted
command can leave); one that is too soon, infeasible or arrives while another runs is
refused, with the reason logged and on ``/diagnostics``. Every second (and on each refusal)
``/diagnostics`` carries the predicted delays with their 95 % bounds, the cycle lock's
state and the drift monitor's alerts on the node's own log.

The ROS clock is the host clock plus an offset measured once at start (``ros_offset_ns``;
ROS time is the system clock unless ``use_sim_time``, which the node does not support).
"""

from __future__ import annotations

import math
import queue
import signal
import tempfile
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from timedexec.drivers import RobotState, open_driver
from timedexec.errors import ConfigError, DriverError, TimedExecError
from timedexec.execution import ExecutorSettings, JointPlan, TimedExecutor
from timedexec.monitoring import DelayMonitor
from timedexec.robots import get_robot_entry
from timedexec.ros._env import import_rclpy, ros_environment
from timedexec.ros._mcap import log_to_mcap, save_node_log, stamp_ns
from timedexec.ros._trajectory import order_joints, plan_from_points

__all__ = ["NodeOptions", "run_node"]

#: Two-sided 95 % normal quantile, for the delay bounds on /diagnostics.
Z95 = 1.959963984540054
#: Slack added to the earliest start of a zero-stamped trajectory, in controller periods.
START_MARGIN_PERIODS = 2
#: Time constants of the position correction the node keeps streaming after a
#: trajectory's end (the residual falls to e^-5 < 1 % of what it was).
SETTLE_TIME_CONSTANTS = 5.0
#: The node's executor options unless given: a position correction with a 50 ms time
#: constant, so that the arm ends at the last point as joint_trajectory_controller's
#: position loop makes it (feed-forward only, the UR10 twin's arm ended up to 6 mrad off
#: on a loaded host; with it 0.01-0.06 mrad), and the cycle lock (commands aimed at the
#: controller's probed intake: without it a command that misses a cycle boundary starts
#: a whole 8 ms cycle later; docs/ros2.md has the figures).
DEFAULT_SETTINGS = {"position_gain_1_s": 20.0, "cycle_lock": True}
#: Log rows kept when no log is written (the monitor follows them first).
KEEP_ROWS = 100_000
#: Largest distance between the arm and a trajectory's first point at time 0, rad.
START_TOLERANCE_RAD = 0.005

OK, WARN, ERROR = 0, 1, 2


@dataclass(frozen=True, kw_only=True)
class NodeOptions:
    """What ``timedexec ros`` runs.

    Parameters
    ----------
    robot_url : str
        The driver's URL (``ur://HOST``, ``rsi://PORT``, ``sim://ROBOT?realtime=1``).
    model : str
        A model bundle directory or a shipped model's name.
    namespace : str
        The node's namespace ("": the root).
    joint_names : 6 str or None
        Joint names to publish and accept (default: the robot's conventional names).
    domain_id : int or None
        ROS domain id (default: ``ROS_DOMAIN_ID`` or 0).
    localhost_only : bool
        Discover peers on this machine only.
    log_path, mcap_path : path or None
        Where to write the node's log (.npz, a cycle log ``timedexec monitor`` reads) and
        the same as MCAP, at exit.
    diagnostics_period_s : float
        Seconds between ``/diagnostics`` arrays.
    settings : ExecutorSettings or None
        The executor's options (default: :data:`DEFAULT_SETTINGS`, a position correction
        of 20 1/s and the cycle lock; the executor's own defaults have neither).
    """

    robot_url: str
    model: str
    namespace: str = ""
    joint_names: tuple[str, ...] | None = None
    domain_id: int | None = None
    localhost_only: bool = False
    log_path: str | None = None
    mcap_path: str | None = None
    diagnostics_period_s: float = 1.0
    settings: ExecutorSettings | None = None

    def __post_init__(self) -> None:
        if self.joint_names is not None and (
            len(self.joint_names) != 6 or len(set(self.joint_names)) != 6
        ):
            raise ConfigError(
                f"joint_names={self.joint_names!r}: give six distinct names, in the order of "
                "joints 1..6"
            )
        if not (math.isfinite(self.diagnostics_period_s) and 0.05 <= self.diagnostics_period_s <= 60):
            raise ConfigError(
                f"diagnostics_period_s={self.diagnostics_period_s!r} outside 0.05 .. 60 s"
            )


class _Stop(Exception):
    """Raised inside an execution when SIGINT or SIGTERM asked the node to stop."""


class _Node:
    """The node's state between the ROS callbacks and the executor's loop."""

    def __init__(
        self,
        options: NodeOptions,
        ex: TimedExecutor,
        rclpy: Any,
        context: Any,
        stop_requested: threading.Event,
    ) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.options = options
        self.ex = ex
        self.robot = str(ex.model.robot)
        entry = get_robot_entry(self.robot)
        self.names = tuple(options.joint_names or entry.joint_names)
        node = self.node = rclpy.create_node(
            "timedexec", namespace=options.namespace or None, context=context
        )
        node.declare_parameter("robot_url", options.robot_url)
        node.declare_parameter("model", options.model)
        node.declare_parameter("joint_names", list(self.names))
        self.logger = node.get_logger()
        self._js_type = JointState
        self._diag_type = DiagnosticArray
        self.pub_js = node.create_publisher(JointState, "joint_states", 100)
        self.pub_diag = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.inbox: queue.Queue[Any] = queue.Queue()
        node.create_subscription(JointTrajectory, "~/joint_trajectory", self.inbox.put, 10)
        self.offset_ns = node.get_clock().now().nanoseconds - round(ex.now() * 1e9)
        self.samples: list[float] = []
        self.diagnostics: list[dict[str, Any]] = []
        self.monitor = DelayMonitor(ex.model)
        self.alerts: list[str] = []
        self.last_trajectory: tuple[int, str] = (OK, "none received")
        self.running_until_s = -math.inf
        self.stop_requested = stop_requested
        self._last_seq: int | None = None

    # ------------------------------------------------------------------ per package
    def publish_state(self, state: RobotState) -> None:
        """Publish ``state`` on ``joint_states``, stamped when it was measured (a coasted
        cycle, which repeats the previous package, is logged but not published)."""
        # Arrival back-dated by the predicted response delay in force (with the cycle lock
        # the executor itself dates packages by the probed sampling boundary instead).
        sample = state.host_time_s - self.ex.estimate(state.host_time_s).response_delay_s
        self.samples.append(sample)
        if state.sequence == self._last_seq:
            return
        self._last_seq = state.sequence
        msg = self._js_type()
        ns = stamp_ns(sample, self.offset_ns)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        msg.name = list(self.names)
        msg.position = [float(x) for x in state.q]
        msg.velocity = [float(x) for x in state.qd]
        self.pub_js.publish(msg)

    def on_step(self, state: RobotState) -> None:
        """During an execution: publish, refuse what arrives meanwhile, obey a stop."""
        self.publish_state(state)
        if self.stop_requested.is_set():
            raise _Stop
        while not self.inbox.empty():
            self.inbox.get_nowait()
            self.refuse(
                "a trajectory runs until "
                f"{stamp_ns(self.running_until_s, self.offset_ns) / 1e9:.3f} s (ROS time); "
                "replacing a running trajectory is not supported: send the next one after it"
            )

    # ------------------------------------------------------------------ trajectories
    def take(self, msg: Any) -> None:
        """Execute a ``JointTrajectory`` (blocking until it has settled) or refuse it.

        Raises
        ------
        _Stop
            A signal asked the node to stop (the executor's context then stops the arm).
        """
        ex = self.ex
        try:
            plan, start_s = self._plan_of(msg)
            running = ex.schedule(plan, start_s)  # refuses a start too soon: nothing sent
        except ConfigError as exc:
            self.refuse(str(exc))
            return
        self.running_until_s = running.end_time_s
        # Stream to the end, then on for the largest shift and three periods (the last
        # commands reach the arm), and with a position correction for five of its time
        # constants (it pulls in what the open-loop stream lost).
        settle_s = ex.lead_time_s(running) + 3 * ex.period_s
        gain = ex.settings.position_gain_1_s
        if gain > 0:
            settle_s += SETTLE_TIME_CONSTANTS / gain
        while ex.now() < running.end_time_s + settle_s:
            self.on_step(ex.step())
        # End the stream (stop returns once the arm reports rest): until the next
        # trajectory the loop only reads, so the next one's preparation (a model query,
        # tens of ms) is not a stalled stream.
        ex.stop()
        shift = ", ".join(f"{x * 1e3:.1f}" for x in running.meta["actuation_s"])
        self.last_trajectory = (OK, f"executed {len(msg.points)} points; shifts [{shift}] ms")
        self.logger.info(f"trajectory of {len(msg.points)} points done (shifts [{shift}] ms)")
        self.publish_diagnostics(plan=running)

    def _plan_of(self, msg: Any) -> tuple[JointPlan, float]:
        ex = self.ex
        index = order_joints(msg.joint_names, self.names)
        pts = msg.points
        if not pts:
            raise ConfigError("the trajectory has no points; send at least one")
        fields = {
            "positions": [len(p.positions) for p in pts],
            "velocities": [len(p.velocities) for p in pts],
            "accelerations": [len(p.accelerations) for p in pts],
        }
        if any(n != 6 for n in fields["positions"]):
            raise ConfigError(f"every point needs 6 positions; got {fields['positions']}")
        for name in ("velocities", "accelerations"):
            if len(set(fields[name])) != 1 or fields[name][0] not in (0, 6):
                raise ConfigError(f"{name}: give 6 in every point or none; got {fields[name]}")
        times = [p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in pts]
        q = np.array([list(p.positions) for p in pts])[:, index]
        v = np.array([list(p.velocities) for p in pts])[:, index] if fields["velocities"][0] else None
        a = np.array([list(p.accelerations) for p in pts])[:, index] if fields["accelerations"][0] else None  # fmt: skip
        q0 = ex.estimate().q_rad
        if times[0] == 0 and np.max(np.abs(q[0] - q0)) > START_TOLERANCE_RAD:
            j = int(np.argmax(np.abs(q[0] - q0)))
            raise ConfigError(
                f"the first point is at time 0 but joint {j + 1} is {q[0, j] - q0[j]:+.4f} rad "
                f"away from it (more than {START_TOLERANCE_RAD} rad); start the trajectory "
                "where the arm is, or give the first point a time_from_start > 0"
            )
        plan = ex.prepare(plan_from_points(ex.spec, q0, times, q, v, a))
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if stamp == 0:  # now: as soon as the slowest joint's shifted command can leave
            start_s = ex.now() + ex.lead_time_s(plan) + START_MARGIN_PERIODS * ex.period_s
        else:
            start_s = (stamp - self.offset_ns) / 1e9
        return plan, start_s

    def refuse(self, reason: str) -> None:
        """Log a refused trajectory and publish the reason on /diagnostics at once."""
        self.logger.error(f"trajectory refused: {reason}")
        self.last_trajectory = (ERROR, f"refused: {reason}")
        self.publish_diagnostics()

    # ------------------------------------------------------------------ diagnostics
    def publish_diagnostics(self, plan: JointPlan | None = None) -> None:
        """Publish (and log) one DiagnosticArray: delays, cycle lock, monitor, trajectory."""
        ex = self.ex
        robot = f"{self.robot} at {self.options.robot_url}"
        status = [self._delay_status(plan, robot), self._lock_status(robot)]
        status.append(self._monitor_status(robot))
        level, message = self.last_trajectory
        status.append(
            {"level": level, "name": "timedexec: trajectory", "message": message,
             "hardware_id": robot, "values": {}}
        )  # fmt: skip
        ns = stamp_ns(ex.now(), self.offset_ns)
        self.diagnostics.append({"stamp_ns": ns, "status": status})
        msg = self._diag_type()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

        for s in status:
            d = DiagnosticStatus()
            d.level = bytes([s["level"]])
            d.name, d.message, d.hardware_id = s["name"], s["message"], s["hardware_id"]
            d.values = [KeyValue(key=k, value=str(v)) for k, v in s["values"].items()]
            msg.status.append(d)
        self.pub_diag.publish(msg)

    def _delay_status(self, plan: JointPlan | None, robot: str) -> dict[str, Any]:
        ex = self.ex
        values: dict[str, str] = {}
        if plan is not None:  # the executed plan's delays (no model query in the loop)
            act = np.asarray(plan.meta["predicted_actuation_s"])
            act_std = np.asarray(plan.meta["actuation_std_s"])
            resp = np.full(6, float(plan.meta["response_s"]))
            resp_std = np.full(6, math.nan)
            where = "at the last trajectory's start"
        else:
            p = ex.predict(ex.estimate().q_rad, np.ones(6, dtype=int))
            act, act_std = p.actuation_mean, p.actuation_std
            resp, resp_std = p.response_mean, p.response_std
            where = "at the arm's position (positive directions)"
        for j, name in enumerate(self.names):
            values[f"{name} actuation_s"] = f"{act[j]:.6f}"
            values[f"{name} actuation_95_s"] = f"[{act[j] - Z95 * act_std[j]:.6f}, {act[j] + Z95 * act_std[j]:.6f}]"  # fmt: skip
            values[f"{name} response_s"] = f"{resp[j]:.6f}"
            if math.isfinite(resp_std[j]):
                values[f"{name} response_95_s"] = f"[{resp[j] - Z95 * resp_std[j]:.6f}, {resp[j] + Z95 * resp_std[j]:.6f}]"  # fmt: skip
        return {"level": OK, "name": "timedexec: predicted delays", "message": where,
                "hardware_id": robot, "values": values}  # fmt: skip

    def _lock_status(self, robot: str) -> dict[str, Any]:
        ex = self.ex
        values: dict[str, str] = {"period_s": f"{ex.period_s:.6f}"}
        if ex.send_phase is None:
            level, message = WARN, "off (commands go out as packages arrive)"
        elif ex.intake is not None:
            level, message = OK, "locked on the probed intake"
            values["intake"] = repr(ex.intake)
        else:
            level, message = WARN, f"aiming by the package arrivals: {ex.intake_error}"
        line = ex.clock_line
        if line is not None:
            values["clock_rate"] = f"{line[2]:.9f}"
        return {"level": level, "name": "timedexec: cycle lock", "message": message,
                "hardware_id": robot, "values": values}  # fmt: skip

    def _monitor_status(self, robot: str) -> dict[str, Any]:
        for alert in self.monitor.follow(self.ex):
            line = alert.message()
            self.alerts.append(line)
            self.logger.warning(f"monitor: {line}")
        # Where nothing will be written, forget the rows the monitor has read (the log
        # grows by ~0.2 kB a package, 0.4 GB an hour at 500 Hz).
        keep = self.options.log_path is not None or self.options.mcap_path is not None
        if not keep and len(self.ex.log) > KEEP_ROWS:
            self.ex.log.clear()
            self.samples.clear()
        values = {f"alert {i + 1}": a for i, a in enumerate(self.alerts[-10:])}
        values["verdict"] = self.monitor.verdict()
        level = WARN if self.alerts else OK
        message = f"{len(self.alerts)} alert(s)" if self.alerts else "no drift alert"
        return {"level": level, "name": "timedexec: drift monitor", "message": message,
                "hardware_id": robot, "values": values}  # fmt: skip


def run_node(options: NodeOptions, *, ready: Callable[[str], None] | None = None) -> int:
    """Run the node until SIGINT or SIGTERM (exit 0, the arm stopped first).

    Parameters
    ----------
    options : NodeOptions
        What to run.
    ready : callable, optional
        Called with one line once the node publishes.

    Returns
    -------
    int
        0 after a stop asked for by a signal.

    Raises
    ------
    ConfigError
        rclpy missing (``pip install 'timedexec[ros]'``), a bad option or model.
    DriverError
        The robot was lost (no state, a stale stream, a refused command): the node logged
        it and stopped; the CLI exits 3.
    """
    ros_environment(domain_id=options.domain_id, localhost_only=options.localhost_only)
    rclpy = import_rclpy()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    settings = options.settings or ExecutorSettings.from_dict(DEFAULT_SETTINGS)
    ex = TimedExecutor(open_driver(options.robot_url), options.model, settings)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node: _Node | None = None
    spinner: threading.Thread | None = None
    executor = None
    try:
        # The ROS side first: once connected, the loop must read every package (a
        # real-time sim:// computes its cycles as they are read and falls behind a pause).
        node = _Node(options, ex, rclpy, context, stop)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node.node)
        spinner = threading.Thread(target=executor.spin, name="rclpy-spin", daemon=True)
        spinner.start()
        with ex:
            _loop(node, stop, ready)
        return 0
    except DriverError as exc:
        if node is not None:
            node.logger.fatal(f"lost the robot at {options.robot_url}: {exc}; the node stops")
        raise DriverError(f"lost the robot at {options.robot_url}: {exc}") from exc
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if node is not None:
            _write_logs(node)
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.node.destroy_node()
        rclpy.shutdown(context=context)
        if spinner is not None:
            spinner.join(timeout=2.0)


def _loop(node: _Node, stop: threading.Event, ready: Callable[[str], None] | None) -> None:
    ex = node.ex
    next_diag = ex.now()  # the first array after the first package
    if ready is not None:
        ready(
            f"node {node.node.get_fully_qualified_name()}: {node.robot} at {node.options.robot_url}, period "
            f"{ex.period_s * 1e3:.1f} ms, joints {', '.join(node.names)}"
        )
    while not stop.is_set():
        try:
            msg = node.inbox.get_nowait()
        except queue.Empty:
            msg = None
        if msg is not None:
            try:
                node.take(msg)
            except _Stop:
                break
            next_diag = ex.now() + node.options.diagnostics_period_s
            continue
        node.publish_state(ex.step())
        if ex.now() >= next_diag:
            node.publish_diagnostics()
            next_diag += node.options.diagnostics_period_s * max(1, math.ceil((ex.now() - next_diag) / node.options.diagnostics_period_s))  # fmt: skip
    # Leaving the executor's context stops a moving arm (returning at rest) and closes it.
    node.logger.info("stop requested: stopping the arm and closing the driver")


def _write_logs(node: _Node) -> None:
    """The node's log (and its MCAP) as asked for; errors are logged, not raised."""
    opts = node.options
    if opts.log_path is None and opts.mcap_path is None:
        return
    ex = node.ex
    arrays = ex.log.arrays()
    n = len(arrays["arrival_s"])
    sample = np.asarray(node.samples[:n] + [math.nan] * (n - len(node.samples)))
    try:
        with tempfile.TemporaryDirectory() as tmp:
            log = Path(opts.log_path) if opts.log_path else Path(tmp) / "log.npz"
            save_node_log(
                log, arrays, sample_s=sample, period_s=ex.period_s, robot=node.robot,
                joint_names=node.names, ros_offset_ns=node.offset_ns,
                diagnostics=node.diagnostics,
            )  # fmt: skip
            if opts.mcap_path:
                log_to_mcap(log, opts.mcap_path)
    except (TimedExecError, OSError) as exc:
        node.logger.error(f"could not write the log: {exc}")
