"""An independently written Universal Robots controller peer for the real ``ur_rtde`` client.

Run it as a process (the folder ``tests`` on the path; standard library only)::

    PYTHONPATH=tests python -m independent_ur_peer --host 127.0.0.171 --model UR10 \\
        --version 5.11.1 --truth /tmp/truth.csv

It listens on the ports the ``ur_rtde`` 1.6.5 client uses (fixed by the client, so one peer per
loopback address): 30004 RTDE (protocol v2), 29999 dashboard and 30003 script upload, prints
``ready`` on stdout once listening, and exits cleanly on SIGTERM.

What it emulates, from UR's public documentation and the control script embedded in
``librtde.so.1.6.5`` (never from this project's own simulator):

* RTDE output recipes streamed at the requested frequency (500 Hz controller cycle for an
  e-Series, version 5.x; 125 Hz for a CB3, version 3.x), packed with the controller's types;
  unknown names answered ``NOT_FOUND``; input recipes numbered 1, 2, 3 ... per connection; an
  input already owned by another connection answered ``IN_USE``.
* The uploaded ``rtde_control`` script's main loop, *not* by interpreting URScript but by
  re-implementing its semantics: command id in ``input_int_register_0`` (or 24), sampled once per
  controller cycle; acknowledgement in ``output_int_register_0`` (1 ready, 2 done); realtime
  commands (9 speedj, 11 servoj, ...) processed every cycle; the others once, until the client
  clears the register; blocking commands (synchronous movej, stopj, speed_stop) keep the main
  loop busy until the motion ends.
* The speed "thread": ``speedj(target, a, t)`` re-issued with the latest target each time the
  previous call returns (after ``t``, or when the target speed is reached when ``t`` is 0), so
  ``t`` never ends the motion; only speed_stop, another motion command or a program stop does.
* ``rtde_set_watchdog(var, f, "stop")``: when no RTDE input package containing ``var`` arrives
  for ``1/f`` s the program is stopped (runtime_state 1) and the arm decelerates to rest;
  watchdogs are removed on program stop.

Physics (deliberately unlike a first-order model): per joint a reference velocity, acceleration
limited to the commanded ``a`` with the leading axis scaling all joints (so a joint-space
straight line), joint speed limits by the same scaling, and a fixed 3-cycle actuation pipeline
(actual velocity = reference velocity 3 cycles earlier); with ``--servo-friction F`` the
actual joint instead follows that delayed reference through a PD position servo (8 Hz,
damping 0.9) against Coulomb friction ``F`` and viscous friction, sticking where the drive
cannot overcome static friction (``Arm``). A program stop decelerates the
reference at ``--stop-decel`` (default 3 rad/s^2, leading axis). The controller clock is a
fixed-rate loop on absolute ``time.monotonic`` deadlines; timestamps are ``cycles * period``.

Truth log (``--truth``): a header comment with ``t0_monotonic``, then the line
``time_s,runtime_state,q0..q5,qd0..qd5`` and one row per controller cycle (actual joint
positions in rad, velocities in rad/s, time in controller seconds), flushed every ~50 ms, plus
``#event,time_s,kind,key=value;...`` lines (program start/stop, watchdog trips, at_rest, ...).

The pendant program with the External Control URCap (``--urcap HOST:PORT``, default
``127.0.0.1:50002``; ``--external-control-program PATH``, default
``/programs/external_control.urp``): for cells where remote control is forbidden the operator
plays a pendant program holding the URCap's *External Control* node. The URCap's installation
names a PC address and port; when the program starts the URCap connects there, sends
``request_program\n`` and reads back a URScript text, which it splits at the markers
``# HEADER_BEGIN`` / ``# HEADER_END`` (function definitions, inserted once) and runs the rest
(``# NODE_CONTROL_LOOP_BEGINS`` ... ``# NODE_CONTROL_LOOP_ENDS``) at its node
(UniversalRobots/Universal_Robots_ExternalControl_URCap, README and ``RequestProgram.java``;
the script is requested anew at every program start). Here:

* The dashboard knows exactly one installed program, that path: ``load`` of it answers
  ``Loading program: <path>``, any other path ``File not found: <path>`` (PolyScope 3.4+ / 5.x
  replies); ``get loaded program`` answers ``Loaded program: <path>`` (``No program loaded``
  before); ``programState`` names the loaded program's file (``<unnamed>`` without one).
* ``play`` with it loaded (and the program stopped) fetches the script as the URCap does, with
  bounds (connect ``URCAP_CONNECT_TIMEOUT_S``; the whole exchange ``URCAP_FETCH_TIMEOUT_S``;
  lines of at most ``MAX_URCAP_LINE`` bytes, ``MAX_URCAP_SCRIPT`` in all). The text is complete
  at the ``# NODE_CONTROL_LOOP_ENDS`` line (ur_rtde's script server keeps the connection open
  after it) or when the PC closes the connection with no marked part left open. Then the program
  starts through the same path as an uploaded script and ``play`` answers ``Starting program``.
  Nobody listening, a timeout, an oversized or incomplete text: ``Failed to execute: play``, a
  ``urcap_fetch_failed`` event, and the program stays STOPPED. (The real URCap instead runs a
  blocking popup program saying "Receive program failed"; for a client either way the program
  never runs.) ``play`` while PAUSED resumes; while PLAYING it changes nothing.
* A fetched text is run with the ``rtde_control`` semantics when it is ur_rtde's control script:
  the four markers in order, a header defining ``rtde_cmd``, ``signal_ready`` and
  ``process_cmd``, and a control loop calling ``rtde_cmd`` and ``process_cmd`` (the uploaded
  form is recognised as before, by its ``rtde_control`` name). Register offsets are read from
  the ``global reg_offset_int = # int register offset`` line, whose value ur_rtde 1.6.5 writes on
  the next line (in the uploaded script too).
* ``load`` while a program runs is refused (``Error while loading program: <path>``, event
  ``load_refused``): the documented failure reply, for a case the document does not describe.

Deliberate simplifications: no kinematics (TCP fields are zero; speedl, movel and other
Cartesian commands stop the program with an ``unsupported_command`` event rather than pretend);
stopl is executed as a joint-space stop; when a new motion command arrives while another
script thread is moving the arm, the newest command takes the arm and the older thread is ended
(the real controller's behaviour with two moving threads is not documented).

For tests, :func:`run_peer` starts the peer in a subprocess and yields a :class:`PeerHandle`::

    from independent_ur_peer import run_peer  # with tests/ on sys.path

    with run_peer("127.0.0.181", model="UR10", version="5.11.1") as peer:
        ...  # point rtde_control / rtde_receive, or the code under test, at peer.host
        trip = peer.wait_event("watchdog_trip", timeout=3.0)  # PeerEvent(time_s, kind, fields)
        truth = peer.wait_truth_until(trip.time_s + 0.3)  # Truth: t, runtime_state, q, qd
        rest = truth.rest_time_after(trip.time_s)  # controller s, None if still moving
        t_peer = peer.to_peer_time(time.monotonic())  # this machine's clock -> controller s

Pick a distinct loopback address per concurrently running peer (the client fixes the ports).

The package, one module per concern (none imports ``timedexec``; the modules import each
other without a circle):

* :mod:`.constants` — the documented numbers: ports, bounds, program states, the pipeline;
* :mod:`.codec` — the RTDE variables, their types and struct formats;
* :mod:`.physics` — the arm: reference, pipeline, motions, the friction servo;
* :mod:`.script` — the ``rtde_control`` script's semantics (commands, script threads);
* :mod:`.urcap` — the External Control URCap's script request and recognition;
* :mod:`.controller` — the cycle, registers, program state, watchdogs, truth log;
* :mod:`.rtde`, :mod:`.dashboard`, :mod:`.server` — the three ports and the process;
* :mod:`.handle` — :func:`run_peer` and :class:`PeerHandle` for tests.
"""

from __future__ import annotations

from .constants import (
    DASHBOARD_PORT,
    DEFAULT_EXTERNAL_CONTROL_PROGRAM,
    DEFAULT_URCAP,
    MAX_URCAP_LINE,
    MAX_URCAP_SCRIPT,
    PIPELINE_CYCLES,
    RTDE_PORT,
    SCRIPT_PORT,
)
from .handle import PeerEvent, PeerHandle, Truth, run_peer
from .server import main
from .urcap import (
    fetch_urcap_script,
    is_rtde_control_script,
    register_offset,
    split_external_control,
)

__all__ = [
    "DASHBOARD_PORT",
    "DEFAULT_EXTERNAL_CONTROL_PROGRAM",
    "DEFAULT_URCAP",
    "MAX_URCAP_LINE",
    "MAX_URCAP_SCRIPT",
    "PIPELINE_CYCLES",
    "RTDE_PORT",
    "SCRIPT_PORT",
    "PeerEvent",
    "PeerHandle",
    "Truth",
    "fetch_urcap_script",
    "is_rtde_control_script",
    "main",
    "register_offset",
    "run_peer",
    "split_external_control",
]
