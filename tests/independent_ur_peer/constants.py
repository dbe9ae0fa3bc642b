"""The controller's documented numbers: ports, package and line bounds, the External Control
URCap's request, program states and modes, the actuation pipeline.
"""

from __future__ import annotations

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

MAX_RTDE_PACKAGE = 16384  # bytes; larger declared sizes close the connection
MAX_DASHBOARD_LINE = 1024  # bytes
MAX_SCRIPT_BYTES = 2 * 1024 * 1024  # bytes buffered from one script connection
MAX_CONNECTIONS = 16  # concurrent connections per port
MAX_RECIPES = 255  # recipe ids are one byte; more setups close the connection
OUTPUT_QUEUE_PACKAGES = 64  # data packages queued per RTDE connection before dropping

# The External Control URCap's script request (see the module docstring).
URCAP_REQUEST = b"request_program\n"
URCAP_CONNECT_TIMEOUT_S = 2.0  # s to connect to the PC (the URCap itself waits 5 s)
URCAP_FETCH_TIMEOUT_S = 3.0  # s for the whole request, connect included
MAX_URCAP_LINE = 4096  # bytes in one line of the received script (ur_rtde 1.6.5: 218)
MAX_URCAP_SCRIPT = 1024 * 1024  # bytes in the whole received script (ur_rtde 1.6.5: 42 kB)
DEFAULT_URCAP = "127.0.0.1:50002"  # the URCap installation's PC address (port 50002 default)
DEFAULT_EXTERNAL_CONTROL_PROGRAM = "/programs/external_control.urp"
HEADER_BEGIN, HEADER_END = "# HEADER_BEGIN", "# HEADER_END"
LOOP_BEGINS, LOOP_ENDS = "# NODE_CONTROL_LOOP_BEGINS", "# NODE_CONTROL_LOOP_ENDS"

STOPPED, PLAYING, PAUSED = 1, 2, 3
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
JOINT_MODE_RUNNING = 253

PIPELINE_CYCLES = 3
