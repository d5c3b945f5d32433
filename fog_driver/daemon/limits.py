"""Every size, rate, count and time limit of the daemon, in one place, each named with its unit.

A misbehaving client (NDJSON or web) costs the daemon a bounded amount and never delays anybody else; a slow
disk or a silent port costs the acquisition nothing.  The numbers that bound each of those live here; the
modules that enforce them (``connection.py``, ``hub.py``, ``service.py``, ``acquisition.py``, ``commands.py``,
``web/``) import them.

The NDJSON hub's limits, as clients meet them.  Each is a constant here or a ``hub.Hub`` argument
(named here, with its default):

- a line longer than ``max_line_bytes`` (4096) is answered with ``ERROR`` and
  discarded up to its newline; 64 KiB (``MAX_UNTERMINATED_BYTES``) without any
  newline closes the connection;
- invalid JSON, a JSON value that is not an object, a malformed line or an
  unknown command: ``ERROR``, and the connection stays open;
- at most 100 lines per second per client (``MAX_COMMANDS_PER_S``; commands,
  and empty or oversized lines alike): the excess is refused, its first line in
  each second answered with ``ERROR`` and the rest dropped without an answer (a
  flood costs the daemon no line written per line received), and 1000 excess
  lines (``MAX_EXCESS_COMMANDS``) close the connection.  The hub
  handles one 64 KiB chunk of a client's input at a time, then serves the others;
- a client that does not read is dropped: when the oldest line queued for it
  (not yet accepted by the kernel) is older than ``max_backlog_s`` (2 s) the
  connection is closed, logged, and counted.  Data has a short shelf life: the
  daemon never buffers old samples for a slow reader;
- at most ``max_clients`` (64) connections, and ``max_clients_per_peer`` (16)
  from one peer address (an IPv4 address; an IPv6 /64): one more gets one
  ``ERROR`` line and is closed.  On a token-protected daemon clients that have
  not authorized hold at most half of either (``guards.Slots``): a new
  connection that finds no room closes the oldest of them (``ERROR`` "closed to
  make room ..."), so a client with the token finds a slot while fewer than
  the maximum have authorized;
- on a token-protected daemon a client that has not authorized within
  ``auth_deadline_s`` (10 s) of connecting gets ``ERROR`` and is closed;
- wrong ``?AUTH`` tokens are counted per peer address, across connections:
  after 3 (``AUTH_FAILURES_BEFORE_BACKOFF``) each further one blocks the
  address for ``auth_backoff_base_s`` (1 s), doubled each time up to
  ``auth_backoff_max_s`` (300 s); while blocked, no token from the address is
  compared, right or wrong: each is refused with ``ERROR`` "too many failed
  attempts, retry in N s" (and not counted), so the answer tells a guesser
  nothing (one address: at most 2,142 guesses a day, 288 once at the cap).
  An address is forgotten after a right token, and ``auth_backoff_max_s``
  after its last failure or block ended (at most 4096 addresses are remembered,
  ``MAX_THROTTLED_PEERS``; the least recently failed are forgotten first);
- a control command waits ``control_timeout_s`` (30 s) for its answer;
- per-client log lines (connected, disconnected, refused, dropped, failed,
  auth failures, errors of the loop such as failed accepts when out of file
  descriptors) are limited to ``log_lines_per_s`` (5) per event and second,
  and the ones left out are counted in a ``log_lines_suppressed`` line (one a
  second per event at most).

Units: ``_BYTES`` bytes, ``_S`` seconds, ``_HZ`` per second, ``_PER_S`` events per second; a name without a
unit is a count (clients, lines, attempts, samples, batches).
"""

from __future__ import annotations

# The protocol's bounds the client library checks before sending: defined there, once.
from ..client.protocol import MAX_BIAS_S as MAX_BIAS_S  # ?BIAS seconds, at most
from ..client.protocol import MAX_TABLE_DWELL_S as MAX_TABLE_DWELL_S  # ?TABLE dwell_s, at most
from ..client.protocol import MIN_TABLE_DWELL_S as MIN_TABLE_DWELL_S  # ?TABLE dwell_s, at least
from ..client.session import MAX_WATCH_RATE_HZ as MAX_WATCH_RATE_HZ  # ?WATCH's rate_hz: the protocol's one bound
from ..dwells import MAX_TABLE_ANGLE_DEG as MAX_TABLE_ANGLE_DEG  # the one bound, with the dwell

# -- the NDJSON hub: lines ------------------------------------------------------------------------------------

#: A command line longer than this (without its newline) is answered with ERROR and discarded up to its newline.
DEFAULT_MAX_LINE_BYTES = 4096
#: The smallest ``max_line_bytes`` a hub accepts.
MIN_MAX_LINE_BYTES = 16
#: Bytes without a newline after which a client is disconnected.
MAX_UNTERMINATED_BYTES = 64 * 1024
#: Bytes the hub reads from one client at a time before it serves the others.
READ_CHUNK_BYTES = 64 * 1024

# -- the NDJSON hub: commands ---------------------------------------------------------------------------------

#: Lines per second per client (commands, empty or oversized lines) before the excess is refused.
MAX_COMMANDS_PER_S = 100
#: The rate limit's window (s).
COMMAND_WINDOW_S = 1.0
#: Refused (excess) lines after which a client is disconnected.
MAX_EXCESS_COMMANDS = 1000
#: How long a control command (the callback and a Future it returns) may take before the client gets an ERROR.
DEFAULT_CONTROL_TIMEOUT_S = 30.0
#: Worker threads that run the ``control`` callback (off the event loop).
CONTROL_WORKERS = 2

# -- the NDJSON hub: clients ----------------------------------------------------------------------------------

#: A client whose oldest queued line is older than this (s) is dropped (it does not read).
DEFAULT_MAX_BACKLOG_S = 2.0
#: The longest pause (s) between two sweeps for clients that do not read (shorter with a short backlog limit).
SWEEP_EVERY_S = 0.25
#: Connected clients at most; one more gets one ERROR line and is closed.
DEFAULT_MAX_CLIENTS = 64
#: Connected clients from one peer address at most (an IPv4 address, or an IPv6 /64).
DEFAULT_MAX_CLIENTS_PER_PEER = 16
#: SO_SNDBUF of the daemon's client sockets: a non-reading client is noticed in seconds, not megabytes.
CLIENT_SNDBUF_BYTES = 256 * 1024
#: How long a setting changed from another thread (``set_token``, ...) may wait for the hub's loop (s).
SETTING_WAIT_S = 5.0
#: How long ``Hub.stop`` waits for the hub's thread (s).
HUB_STOP_TIMEOUT_S = 5.0

# -- authorization (the NDJSON hub and the web view) ----------------------------------------------------------

#: On a token-protected hub, seconds a client has to ``?AUTH`` after connecting before it is closed.
DEFAULT_AUTH_DEADLINE_S = 10.0
#: Failed (or refused) ``?AUTH`` attempts after which a connection is closed.
MAX_AUTH_FAILURES = 5
#: Wrong tokens from one peer address (across connections, and on the web listener) before the backoff starts.
AUTH_FAILURES_BEFORE_BACKOFF = 3
#: The first backoff after a failed ``?AUTH`` (s); each further failure doubles it.
DEFAULT_AUTH_BACKOFF_BASE_S = 1.0
#: The longest backoff (s); an address is also forgotten this long after its last backoff ended.
DEFAULT_AUTH_BACKOFF_MAX_S = 300.0
#: Peer addresses whose failed ``?AUTH`` attempts are remembered at most (the least recent go first).
MAX_THROTTLED_PEERS = 4096

# -- logging --------------------------------------------------------------------------------------------------

#: Log lines per second at most for each per-client event (connect, disconnect, auth failure, ...).
DEFAULT_LOG_LINES_PER_S = 5
#: The log rate limiter's window (s), and the shortest interval between two summaries of one event.
LOG_WINDOW_S = 1.0

# -- the service ----------------------------------------------------------------------------------------------

#: Samples kept while no IDENTITY has arrived (the frame rate is unknown): 60 s at 2 kHz.  Older ones are
#: dropped and counted (``samples_dropped_before_identity``).
MAX_SAMPLES_BEFORE_IDENTITY = 120_000
#: A ``?BIAS`` capture whose seconds of device time have not arrived within its seconds plus this margin (host
#: time) is abandoned: a ``BIAS`` ``failed`` event, and the bias in use is kept.
BIAS_ANSWER_MARGIN_S = 30.0
#: ``?BIAS`` seconds when the command gives none, and the fewest it accepts (the most: ``MAX_BIAS_S``, above).
DEFAULT_BIAS_S = 60
MIN_BIAS_S = 1
#: The largest ``?ADAPT`` ``reference_dph`` (deg/h, either sign).
MAX_ADAPT_REFERENCE_DPH = 1e7
#: ``?TABLE``: the largest angle (deg, either sign: ``dwells.MAX_TABLE_ANGLE_DEG``, a table log's and a sidecar's
#: too) and the longest dwell (``MAX_TABLE_DWELL_S``) are imported above; the least time between two from one
#: client (more get ERROR):
TABLE_INTERVAL_S = 2.0
#: The port reader is stuck (no watchdog ping) when its loop has not come round for this long.
READER_STALL_S = 10.0
#: Shutdown budget: the acquisition join and the capture's close each get at most this long (the unit's
#: ``TimeoutStopSec`` must exceed their sum plus the hub's stop).
JOIN_TIMEOUT_S = 5.0
#: The port reader's longest wait (s) between two attempts to open a port that went away.
PORT_BACKOFF_MAX_S = 1.0

# -- the web view ---------------------------------------------------------------------------------------------

#: Updates a second sent to every page.
WEB_DEFAULT_UPDATE_HZ = 2.0
#: The most updates a second a web view may be asked for.
WEB_MAX_UPDATE_HZ = 50.0
#: Published batches waiting for the web listener's loop at most (the oldest go first, counted).
WEB_MAX_INBOX_BATCHES = 100_000
#: Connections at most, and from one peer address at most (beyond them the connection is closed at once); those
#: without the token hold at most half of either (``guards.Slots``).
WEB_MAX_CONNECTIONS = 64
WEB_MAX_CONNECTIONS_PER_PEER = 24
#: A connection without the token is closed this long (s) after its first request (an open-stream reader's
#: WebSocket excepted).
WEB_UNAUTHORIZED_LIFETIME_S = 10.0
#: A login's session (its cookie's ``Max-Age``, s), and the sessions kept at most (the oldest end first).
WEB_SESSION_MAX_AGE_S = 12 * 3600
WEB_MAX_SESSIONS = 256
#: The request line and each header at most (431/400), headers at most, a request body at most (413).
WEB_MAX_LINE_BYTES = 4096
WEB_MAX_HEADERS = 40
WEB_MAX_BODY_BYTES = 1024
#: A request head must be complete within this long of the connection or of its first byte (s).
WEB_REQUEST_HEAD_TIMEOUT_S = 10.0
#: A request must be answered within this long (s): a client that does not read its response is closed.
WEB_REQUEST_TIMEOUT_S = 60.0
#: Idle keep-alive connections close after this long (s).
WEB_KEEPALIVE_S = 15.0
#: A WebSocket peer's message at most, and its messages (pings and pongs included) a second at most (the page
#: sends none; a browser answers the listener's ping every ``WEB_WS_HEARTBEAT_S``).
WEB_MAX_WS_MESSAGE_BYTES = 1024
WEB_MAX_WS_MESSAGES_PER_S = 10
#: The WebSocket ping interval (s).
WEB_WS_HEARTBEAT_S = 10.0
#: The window (s) of ``WEB_MAX_WS_MESSAGES_PER_S``.
WEB_WS_WINDOW_S = 1.0
#: The longest pause (s) between two sweeps for slow requests (shorter with a short head timeout).
WEB_SWEEP_EVERY_S = 1.0
#: How long the listener's shutdown waits for requests still running (s).
WEB_SHUTDOWN_TIMEOUT_S = 1.0
#: A page's oldest unsent update older than this (s) drops it, unless the daemon's config says otherwise.
WEB_DEFAULT_MAX_BACKLOG_S = 2.0
#: How long ``WebView.start`` waits for its listener (s), and ``stop`` for its thread (s).
WEB_START_TIMEOUT_S = 30.0
WEB_STOP_TIMEOUT_S = 5.0
