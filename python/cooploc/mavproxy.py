"""cooploc for MAVProxy: the team's cooperative estimates, agreement and link figures.

Load it with ``module load cooploc`` (see tools/mavproxy/README.md for the install and the
``--dialect cooploc`` start). It listens to every link MAVProxy has and never sends anything
unless asked (``cooploc refresh``); it does not change the target system, swallow packets or
block MAVProxy's loop.

What it reads
-------------
- The cooploc dialect (dialects/cooploc.xml): COOPLOC_STATE_FRAGMENT (61000), COOPLOC_RANGE
  (61001), COOPLOC_ESTIMATE (61002), COOPLOC_EPOCH (61003), COOPLOC_STORE_FRAGMENT (61004),
  COOPLOC_RANGE_BEARING (61005), COOPLOC_EPOCH_SET (61006: COOPLOC_EPOCH with its participants
  as a bitmask, what nodes send when their ids span at most 64), COOPLOC_STORE_HELD (61007: what
  a node asking for a store holds of it). With ``--dialect cooploc`` MAVProxy decodes them; under another
  dialect (MAVProxy's default ``all``, or ``ardupilotmega``) they arrive as ``UNKNOWN_610xx`` and
  the module decodes them itself with bindings mavgen makes from the cooploc XML (``$MDEF/v1.0``
  or the repository's ``dialects/``).
- HEARTBEAT, COMMAND_ACK and the frame headers of the companion nodes: system id = platform id,
  component 191 (MAV_TYPE_ONBOARD_CONTROLLER).
- Simulated vehicles (``cooploc sitl``, system id = platform id, component 1): SIM_STATE (the
  truth) and the ``time_usec`` of HIGHRES_IMU and ODOMETRY (the vehicle clock that stamps it).

Per vehicle
-----------
- The latest COOPLOC_ESTIMATE by ``time_usec`` (the same message arrives on several links: an
  older one is ignored, a repeat is not counted twice; a jump back of more than 5 s is a restarted
  node: the track starts over and ``restarts`` counts it).
- The 95 % horizontal error ellipse from the NN, NE, EE entries of ``pos_covariance``:
  semi-axes ``sqrt(5.991464547107979 * eigenvalue)`` (chi-square, 2 dof, 95 %), the bearing of
  the major axis from north towards east in (-90, 90] degrees (as ``cooploc gcs`` gives it).
- Link loss from the MAVLink sequence numbers of the node's frames (source (id, 191)), per
  MAVProxy link, by the library's one rule (``cooploc.SequenceTracker``: a late frame takes its
  loss back, a repeat or a restarted sender is no loss): ``lost / (received + lost)`` in %; estimate rate (estimates a second) and the
  node's bytes a second (frame bytes from (id, 191), a frame seen on two links counted once), both
  over the last 10 s of receive time; whether its frames are signed (MAVLink 2 ``incompat_flags``
  bit 0; pymavlink's ``get_signed()`` is only true for a signature it checked with its own key).
- Validation: a non-finite number, a negative variance, an unknown method, an estimate whose
  ``platform`` (an epoch whose ``announcer``, a range whose ``from_platform``, ...) is not the
  sending system, is counted in ``rejected`` and dropped.

Error against the truth (simulated vehicles): ``cooploc.TruthTrack``, ``cooploc gcs``'s code
----------------------------------------------------------------------------------------------
(``gcs::truth``; the SIM_STATE check and conversion ``cooploc.sim_state_from_frame``)

- Truth: SIM_STATE from (id, 1), its position (``lat_int``/``lon_int`` in 1e-7 degrees when
  non-zero, else ``lat``/``lon``; ``alt``) converted to the team's NED frame about the origin
  (``cooploc origin``) by the inverse of the flat-Earth conversion (``cooploc.geo_to_ned``: the
  longitude difference wrapped to [-180, 180), R = 6378137 m). A non-finite field, a latitude
  outside [-90, 90] or a quaternion whose norm is not 1 is counted in ``rejected``.
- SIM_STATE has no time: a sample takes the ``time_usec`` of the next HIGHRES_IMU or ODOMETRY of
  (id, 1) (a simulator sends the clock-driven messages due at ``t`` just before its samples at
  ``t``); one still waiting when the next SIM_STATE comes is placed at the last known time. The
  last 4096 timed samples are kept in time order: a time more than 5 s back is a restarted
  simulator (they start over), a smaller step back or an equal time is dropped. A frame seen
  again on another link is used once. Changing the origin drops the samples.
- An estimate's error: the truth interpolated linearly at its ``time_usec`` between the
  bracketing samples (at most 1 s apart; none outside the truth's span), the horizontal (N, E)
  distance in m and the position NEES ``e^T P^-1 e`` over N, E, D with P the 3x3 position
  covariance from ``pos_covariance`` (none when P is not positive definite). Estimates come
  before the truth covers their time: the last 64 per vehicle wait, and are resolved when it
  does. Shown: the error and NEES of the newest resolved estimate, and that estimate's time.

Agreement (COOPLOC_EPOCH): ``cooploc.EpochTally``, the library's (``view::health``)
-----------------------------------------------------------------------------------
The rules of ``cooploc gcs``, its page and its Foxglove channels, by the same code: a report is a
COOPLOC_EPOCH in state APPLIED, PARTIAL or FAILED, the first per (epoch, announcer) counting; an
epoch with two or more reports disagrees when two of its (digest, participants) differ (counted
once: ``disagreements``); per vehicle, ``disagreements`` is the epochs its report is outvoted at
(the majority judged again as reports come in, a tie going to the lowest id); a heal is an
agreeing epoch after the latest disagreeing one (withdrawn if a late report disagrees), counted
for the team and per vehicle that reported it; ``partial``, ``failed``, ``store_wanted`` per
vehicle. Bounded: the last 256 epochs and 64 vehicles.

Commands
--------
``cooploc status``: one ``cooploc vehicle <id> key=value ...`` line per vehicle (with
``error_m``, ``nees``, ``error_t_us``, ``truth_samples``; ``-`` when not known) and one
``cooploc team ...`` line. ``cooploc team``: a compact table. ``cooploc origin LAT LON ALT``:
the team's NED origin for the map and the truth (default 34.7 0.0 0.0). ``cooploc refresh [ID]``: asks
node ID (0: every node) for its estimate (COMMAND_LONG MAV_CMD_REQUEST_MESSAGE 512, param1 =
61002, target component 191, on every link); the COMMAND_ACKs are counted per vehicle.
``cooploc graph nis|error|ellipse|rate ID``: a live graph through MAVProxy's graph module (error:
the horizontal error against the truth, m; ellipse: the 95 % semi-major axis, m).
``cooploc set [NAME [VALUE]]``: settings (``statusfile``: append the status lines to this file
every ``status_period`` s; ``map``: draw on MAVProxy's map).

The map (when ``module load map`` works, i.e. wx is installed): a marker per vehicle (its
heading) and its 95 % ellipse, in the colour every cooploc display gives it
(:data:`PALETTE`, index ``(id - 1) mod 10``).
"""

import collections
import math
import os
import sys
import time
import traceback

try:  # MAVProxy is needed to run as a module, not to use the pure functions below.
    from MAVProxy.modules.lib import mp_module
    from MAVProxy.modules.lib import mp_settings
    _MPModule = mp_module.MPModule
except ImportError:  # pragma: no cover - exercised only without MAVProxy installed
    mp_module = None
    mp_settings = None
    _MPModule = object

try:  # The cooploc Python package (python/ of the repository; tests/run-all.sh installs it).
    import cooploc as _cooploc
except ImportError as _e:  # pragma: no cover - a clear message instead of a NameError later
    raise ImportError("the MAVProxy module needs the cooploc Python package: build and install it with "
                      "`maturin develop --release -m python/Cargo.toml` in MAVProxy's environment "
                      "(bash tests/run-all.sh does it for the test virtualenv): %s" % _e) from _e

# ---- constants ------------------------------------------------------------------------------

#: Chi-square quantile, 2 degrees of freedom, 95 % (the library's).
CHI2_2DOF_95 = _cooploc.CHI2_2DOF_95
#: Equatorial radius of the flat-Earth conversion, m (the library's).
EARTH_RADIUS_M = _cooploc.EARTH_RADIUS_M
#: Default NED origin (lat, lon in degrees, alt in m): the same as ``cooploc gcs``.
DEFAULT_ORIGIN = (34.7, 0.0, 0.0)
#: Component id of the cooploc companion nodes.
NODE_COMPID = 191
#: Estimate time going back more than this is a restarted node, us.
RESTART_US = 5_000_000
#: Component id of a simulated vehicle (``cooploc sitl``): its SIM_STATE is the truth.
TRUTH_COMPID = 1
#: Timed truth samples kept per vehicle; estimates held until the truth covers their time.
TRUTH_HISTORY = 4096
PENDING_ESTIMATES = 64
#: Largest gap between two truth samples the error interpolates across, us.
MAX_TRUTH_GAP_US = 1_000_000
#: Window of the rates, s.
RATE_WINDOW_S = 10.0
#: Bounds of the tables.
MAX_VEHICLES = 64
#: Colours of the platforms (index (id - 1) mod 10), shared by every cooploc display: the
#: library's ``view::PALETTE``.
PALETTE = list(_cooploc.PALETTE)

MSG_STATE_FRAGMENT = 61000
MSG_RANGE = 61001
MSG_ESTIMATE = 61002
MSG_EPOCH = 61003
MSG_STORE_FRAGMENT = 61004
MSG_RANGE_BEARING = 61005
MSG_EPOCH_SET = 61006
MSG_STORE_HELD = 61007
COOPLOC_MESSAGE_IDS = frozenset(range(61000, 61008))
#: The two forms of an epoch announcement (the participants as a list, as a bitmask).
EPOCH_MESSAGES = ("COOPLOC_EPOCH", "COOPLOC_EPOCH_SET")

#: The cooploc messages the module only counts, and the VehicleView counter of each.
COUNTED = {"COOPLOC_RANGE": "ranges", "COOPLOC_STATE_FRAGMENT": "state_fragments",
           "COOPLOC_STORE_FRAGMENT": "store_fragments", "COOPLOC_RANGE_BEARING": "range_bearings",
           "COOPLOC_STORE_HELD": "store_held"}

MAV_CMD_REQUEST_MESSAGE = 512
MAVLINK_IFLAG_SIGNED = 1

#: COOPLOC_METHOD, names without the prefix, lower case.
METHODS = {
    0: "dead_reckoning",
    1: "no_propagation",
    2: "decentralized",
    3: "centralized",
    4: "covariance_intersection",
}
#: COOPLOC_EPOCH_STATE.
EPOCH_COLLECTING, EPOCH_APPLIED, EPOCH_PARTIAL, EPOCH_FAILED, EPOCH_STORE_WANTED, EPOCH_NO_RECORD, EPOCH_NO_RANGE = range(7)


# ---- pure functions -------------------------------------------------------------------------

#: The 95 % horizontal error ellipse of an N/E covariance: ``(semi_major_m, semi_minor_m,
#: bearing_deg)`` or None (``cooploc.ellipse95``: the library's, what every cooploc display draws).
ellipse95 = _cooploc.ellipse95


def ellipse_points_ne(north, east, semi_major, semi_minor, bearing_deg, segments=36):
    """Points (N, E) of an ellipse centred at (north, east), its major axis along
    ``bearing_deg`` (from north towards east): ``segments + 1`` points, the last equal to the
    first (a closed polygon), starting at the major axis's forward end."""
    b = math.radians(bearing_deg)
    cb, sb = math.cos(b), math.sin(b)
    points = []
    for k in range(segments + 1):
        t = 2.0 * math.pi * (k % segments) / segments
        u, v = semi_major * math.cos(t), semi_minor * math.sin(t)
        # u along the major axis (cb, sb) in (N, E), v along the minor axis (-sb, cb).
        points.append((north + u * cb - v * sb, east + u * sb + v * cb))
    return points


def ellipse_polygon_latlon(north, east, ellipse, origin=DEFAULT_ORIGIN, segments=36):
    """The 95 % ellipse ``(semi_major, semi_minor, bearing_deg)`` about (north, east) as a closed
    list of (lat, lon), for the map."""
    a, b, bearing = ellipse
    return [_cooploc.ned_to_geo(n, e, 0.0, origin)[:2]
            for n, e in ellipse_points_ne(north, east, a, b, bearing, segments)]


def colour_rgb(platform):
    """The platform's colour as an (r, g, b) tuple of 0..255."""
    h = PALETTE[(int(platform) - 1) % len(PALETTE)]
    return (int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16))


def method_name(value):
    """COOPLOC_METHOD value to its name without prefix, lower case (None if unknown)."""
    return METHODS.get(value)


def fmt_float(v):
    """``repr`` of a float, '-' for NaN (what ``cooploc status`` prints for decoded fields)."""
    return "-" if isinstance(v, float) and math.isnan(v) else repr(v)


class RecentFrames:
    """The last ``size`` frame keys (hashes of their bytes), to take a frame that arrives on
    several links once."""

    def __init__(self, size):
        self.order = collections.deque(maxlen=size)
        self.keys = set()

    def seen(self, key):
        """True if ``key`` is among the last ``size`` keys; remembers it otherwise."""
        if key in self.keys:
            return True
        if len(self.order) == self.order.maxlen:
            self.keys.discard(self.order[0])
        self.order.append(key)
        self.keys.add(key)
        return False


# ---- validation of decoded messages ---------------------------------------------------------

class Rejected(Exception):
    """A message that fails the checks (counted, dropped)."""


def check_message(m):
    """Checks a cooploc message as the node and ``cooploc gcs`` check it, on its frame's bytes
    (``cooploc.check_frame``: the library's ``protocol::wire`` checks, and that the platform it
    speaks for is the sending system); raises :class:`Rejected` naming what is wrong. Returns the
    participants of a COOPLOC_EPOCH or COOPLOC_EPOCH_SET (None for the other messages)."""
    try:
        return _cooploc.check_frame(bytes(m.get_msgbuf()))[1]
    except ValueError as e:
        raise Rejected(str(e)) from None


def frame_header(msgbuf):
    """(msgid, sysid, compid, seq, incompat_flags) of a raw MAVLink 1 or 2 frame, or None."""
    if len(msgbuf) >= 10 and msgbuf[0] == 0xFD:
        return (msgbuf[7] | msgbuf[8] << 8 | msgbuf[9] << 16, msgbuf[5], msgbuf[6], msgbuf[4], msgbuf[2])
    if len(msgbuf) >= 6 and msgbuf[0] == 0xFE:
        return (msgbuf[5], msgbuf[3], msgbuf[4], msgbuf[2], 0)
    return None


# ---- error against truth (simulated vehicles): cooploc.TruthTrack, the ground station's -------

#: Position NEES over N, E, D from the error and the six covariance entries of the wire, or None
#: unless P is positive definite (``cooploc.position_nees``: the library's).
position_nees = _cooploc.position_nees


# ---- the dialect when MAVProxy runs another one -----------------------------------------------

def find_dialect_xml():
    """cooploc.xml: ``$MDEF/v1.0/cooploc.xml``, else the repository's ``dialects/cooploc.xml``
    (this file is ``python/cooploc/mavproxy.py`` of the repository, installed editable by
    ``tests/run-all.sh``; None if neither exists)."""
    candidates = []
    if os.environ.get("MDEF"):
        candidates.append(os.path.join(os.environ["MDEF"], "v1.0", "cooploc.xml"))
    here = os.path.dirname(os.path.realpath(__file__))
    candidates.append(os.path.join(here, "..", "..", "dialects", "cooploc.xml"))
    for c in candidates:
        if os.path.isfile(c):
            return os.path.normpath(c)
    return None


def generate_bindings(xml_path):
    """pymavlink bindings (MAVLink 2) generated by mavgen from ``xml_path`` into a temporary
    directory and imported under a private name; returns the module."""
    import contextlib
    import importlib.util
    import io
    import shutil
    import tempfile
    from pymavlink.generator import mavgen
    out_dir = tempfile.mkdtemp(prefix="mavproxy-cooploc-")
    try:
        out = os.path.join(out_dir, "cooploc_bindings.py")
        opts = mavgen.Opts(out, wire_protocol="2.0", language="Python3", validate=False)
        with contextlib.redirect_stdout(io.StringIO()):
            if not mavgen.mavgen(opts, [xml_path]):
                raise RuntimeError("mavgen refused %s" % xml_path)
        spec = importlib.util.spec_from_file_location("_mavproxy_cooploc_bindings", out)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    finally:
        # (the module is loaded: its folder is not left behind at every `module load`)
        shutil.rmtree(out_dir, ignore_errors=True)


# ---- the module ---------------------------------------------------------------------------------

class VehicleView:
    """What the module knows of one platform."""

    def __init__(self, vid, now):
        self.id = vid
        self.created = now
        self.est = None             # the latest COOPLOC_ESTIMATE (pymavlink message)
        self.est_payload = None
        self.ellipse = None
        self.est_rate = _cooploc.RateWindow(RATE_WINDOW_S)  # the ground station's (gcs::link)
        self.bytes_rate = _cooploc.RateWindow(RATE_WINDOW_S)
        self.signed_rate = _cooploc.RateWindow(RATE_WINDOW_S)
        self.unsigned_rate = _cooploc.RateWindow(RATE_WINDOW_S)
        self.recent_frames = RecentFrames(128)
        self.loss = {}              # MAVProxy link number -> cooploc.SequenceTracker of (id, 191)
        self.hb_time = None
        self.hb_type = None
        self.estimates = 0
        self.repeats = 0
        self.stale = 0
        self.restarts = 0
        self.rejected = 0
        self.state_fragments = 0
        self.store_fragments = 0
        self.store_held = 0
        self.ranges = 0
        self.range_bearings = 0
        self.acks = 0
        self.acks_refused = 0
        self.map_drawn = False

    def seen_frame(self, key):
        """True if this frame (its bytes' hash) was seen lately on another link."""
        return self.recent_frames.seen(key)

    def signed_text(self, now):
        s, u = self.signed_rate.total(now), self.unsigned_rate.total(now)
        if s == 0 and u == 0:
            return "-"
        return "yes" if u == 0 else ("no" if s == 0 else "mixed")

    def loss_text(self):
        if not self.loss:
            return "-"
        return ",".join("%d:%.2f" % (link, 100.0 * (self.loss[link].loss_fraction() or 0.0)) for link in sorted(self.loss))


class CooplocModule(_MPModule):
    """MAVProxy module ``cooploc`` (see the module docstring)."""

    def __init__(self, mpstate):
        super(CooplocModule, self).__init__(mpstate, "cooploc", "cooperative localization (cooploc) team view",
                                            public=True, multi_vehicle=True)
        self.vehicles = {}
        self.epochs = _cooploc.EpochTally()  # the library's rules (view::health)
        self.origin = DEFAULT_ORIGIN
        self.vehicles_refused = 0
        self.truths = {}             # system id -> cooploc.TruthTrack (the ground station's rules)
        self.truth_frames = {}       # system id -> RecentFrames of its truth link (a frame on two links once)
        self.last_rejected = None
        self.rejected_unknown = 0    # rejected messages of systems without a place in the table
        self.undecoded = 0           # cooploc frames no bindings could decode
        self.refresh_sent = 0
        self.errors = 0
        self.last_error = None
        self._tracebacks_shown = 0
        self._last_status = 0.0
        self._last_file = 0.0
        self._last_map = 0.0
        self._graphs = []            # (graph, vehicle id, kind)
        self._hooked = []
        self.settings_cooploc = mp_settings.MPSettings([
            ("statusfile", str, ""),
            ("status_period", float, 1.0),
            ("map", bool, True),
            ("map_period", float, 1.0),
        ])
        self.add_command("cooploc", self.cmd_cooploc, "cooperative localization team view",
                         ["status", "team", "origin", "refresh", "graph <nis|error|ellipse|rate>",
                          "set (COOPLOCSETTING)"])
        self.add_completion_function("(COOPLOCSETTING)", self.settings_cooploc.completion)
        self.bindings = None
        self.bindings_note = None
        self._mav = None
        self._setup_bindings()
        self._hook_links()

    # ---- set-up -------------------------------------------------------------------------------

    def _setup_bindings(self):
        """Own bindings when MAVProxy's dialect lacks the cooploc messages."""
        from pymavlink import mavutil
        if hasattr(mavutil.mavlink, "MAVLINK_MSG_ID_COOPLOC_ESTIMATE"):
            return
        xml = find_dialect_xml()
        if xml is None:
            self.bindings_note = ("MAVProxy's dialect has no cooploc messages and no cooploc.xml was found: "
                                  "start MAVProxy with MDEF and --dialect cooploc (tools/mavproxy/README.md)")
        else:
            try:
                self.bindings = generate_bindings(xml)
                self._mav = self.bindings.MAVLink(None)
                self.bindings_note = ("MAVProxy's dialect (%s) has no cooploc messages: decoding them with bindings "
                                      "from %s" % (getattr(mavutil, "current_dialect", "?"), xml))
            except Exception as e:
                self.bindings_note = "no cooploc bindings: %s" % e
        print("cooploc: " + self.bindings_note)

    def _hook_links(self):
        """Per-link frame accounting: a message hook on every MAVProxy link (links added later
        are hooked from idle_task)."""
        for master in self.mpstate.mav_master:
            hooks = getattr(master, "message_hooks", None)
            if hooks is not None and self._link_hook not in hooks:
                hooks.append(self._link_hook)
                self._hooked.append(master)

    def unload(self):
        for master in self._hooked:
            try:
                master.message_hooks.remove(self._link_hook)
            except (AttributeError, ValueError):
                pass
        self._hooked = []
        self._map_clear()
        self.remove_command("cooploc")
        super(CooplocModule, self).unload()

    # ---- errors -------------------------------------------------------------------------------

    def _error(self, where, e):
        """A programming error (or a message no check foresaw): counted, remembered, the first
        few shown with their traceback; MAVProxy goes on."""
        self.errors += 1
        self.last_error = "%s: %s: %s" % (where, type(e).__name__, e)
        if self._tracebacks_shown < 3:
            self._tracebacks_shown += 1
            print("cooploc: error in %s (counted, MAVProxy goes on; `cooploc status` shows the last):" % where)
            traceback.print_exc(file=sys.stdout)

    # ---- vehicles -----------------------------------------------------------------------------

    def _vehicle(self, sysid, now):
        v = self.vehicles.get(sysid)
        if v is not None:
            return v
        if not 1 <= sysid <= 255:
            return None
        if len(self.vehicles) >= MAX_VEHICLES:
            self.vehicles_refused += 1
            return None
        v = self.vehicles[sysid] = VehicleView(sysid, now)
        return v

    def _reject(self, sysid, reason):
        v = self.vehicles.get(sysid)
        if v is not None:
            v.rejected += 1
        else:
            self.rejected_unknown += 1
        self.last_rejected = reason

    # ---- packets ------------------------------------------------------------------------------

    def _link_hook(self, master, msg):
        """pymavlink message hook (every message of every link, before the modules see it):
        sequence loss, bytes and signing of the nodes' frames (source (id, 191))."""
        try:
            if msg.get_type() == "BAD_DATA":
                return
            buf = msg.get_msgbuf()
            if msg.get_msgId() < 0:
                h = frame_header(buf)
                if h is None:
                    return
                _, sysid, compid, seq, flags = h
            else:
                hdr = msg.get_header()
                sysid, compid, seq, flags = hdr.srcSystem, hdr.srcComponent, hdr.seq, hdr.incompat_flags
            if compid != NODE_COMPID:
                return
            now = time.monotonic()
            v = self._vehicle(sysid, now)
            if v is None:
                return
            link = getattr(master, "linknum", 0)
            loss = v.loss.get(link)
            if loss is None:
                loss = v.loss[link] = _cooploc.SequenceTracker()
            loss.observe(seq)
            if not v.seen_frame(hash(bytes(buf))):
                v.bytes_rate.add(now, len(buf))
                (v.signed_rate if flags & MAVLINK_IFLAG_SIGNED else v.unsigned_rate).add(now)
        except Exception as e:
            self._error("link hook", e)

    def mavlink_packet(self, m):
        """Every packet of every link (the module is multi-vehicle); never raises."""
        try:
            self._packet(m)
        except Exception as e:
            self._error("mavlink_packet %s" % m.get_type(), e)

    def _decoded(self, m):
        """The cooploc message (or HEARTBEAT / COMMAND_ACK) ``m`` stands for, or None."""
        mtype = m.get_type()
        if not mtype.startswith("UNKNOWN_"):
            return m
        h = frame_header(m.get_msgbuf())
        if h is None or h[0] not in COOPLOC_MESSAGE_IDS:
            return None
        if self._mav is None:
            self.undecoded += 1
            return None
        try:
            return self._mav.decode(bytearray(m.get_msgbuf()))
        except Exception as e:  # a bad CRC or length: the frame is not a valid cooploc message
            self._reject(h[1], "undecodable %s: %s" % (mtype, e))
            return None

    def _packet(self, m):
        m = self._decoded(m)
        if m is None:
            return
        mtype = m.get_type()
        sysid, compid = m.get_srcSystem(), m.get_srcComponent()
        if mtype == "HEARTBEAT":
            if compid == NODE_COMPID:
                v = self._vehicle(sysid, time.monotonic())
                if v is not None:
                    v.hb_time = time.monotonic()
                    v.hb_type = m.type
            return
        if mtype == "COMMAND_ACK":
            # Acks of our REQUEST_MESSAGE: addressed to this ground station (or to every one).
            ours = getattr(getattr(self.mpstate, "settings", None), "source_system", 255)
            if compid == NODE_COMPID and m.command == MAV_CMD_REQUEST_MESSAGE and m.target_system in (0, ours):
                v = self.vehicles.get(sysid)
                if v is not None:
                    if m.result == 0:
                        v.acks += 1
                    else:
                        v.acks_refused += 1
            return
        if compid == TRUTH_COMPID and mtype in ("SIM_STATE", "HIGHRES_IMU", "ODOMETRY"):
            self._truth_message(m, mtype, sysid)
            return
        if mtype != "COOPLOC_ESTIMATE" and mtype not in EPOCH_MESSAGES and mtype not in COUNTED:
            return
        now = time.monotonic()
        try:
            participants = check_message(m)
            v = self._vehicle(sysid, now)
            if v is None:
                return
            if mtype == "COOPLOC_ESTIMATE":
                self._estimate(v, m, now)
            elif mtype in EPOCH_MESSAGES:
                self.epochs.add(m.epoch, m.announcer, m.state, m.digest, participants)
            else:
                setattr(v, COUNTED[mtype], getattr(v, COUNTED[mtype]) + 1)
        except Rejected as r:
            self._reject(sysid, str(r))

    def _truth(self, sysid):
        """The TruthTrack of system ``sysid`` (made on first use; at most MAX_VEHICLES, refusals
        counted in ``vehicles_refused``), or None."""
        track = self.truths.get(sysid)
        if track is None and 1 <= sysid <= 255:
            if len(self.truths) >= MAX_VEHICLES:
                self.vehicles_refused += 1
                return None
            track = self.truths[sysid] = _cooploc.TruthTrack(TRUTH_HISTORY, PENDING_ESTIMATES, MAX_TRUTH_GAP_US, RESTART_US)
            self.truth_frames[sysid] = RecentFrames(64)
        return track

    def _truth_message(self, m, mtype, sysid):
        """SIM_STATE, HIGHRES_IMU or ODOMETRY of the simulated vehicle (sysid, 1): the truth and
        the clock that stamps it."""
        if mtype == "SIM_STATE":
            try:  # the ground station's check and conversion (protocol::wire)
                ned = _cooploc.sim_state_from_frame(bytes(m.get_msgbuf() or b""), self.origin)
            except ValueError as r:
                self._reject(sysid, str(r))
                return
        else:
            t = m.time_usec
            if not isinstance(t, int) or t < 0:
                self._reject(sysid, "%s.time_usec %r" % (mtype, t))
                return
        track = self._truth(sysid)
        if track is None or self.truth_frames[sysid].seen(hash(bytes(m.get_msgbuf() or b""))):
            return
        resolved = track.sim_state(ned) if mtype == "SIM_STATE" else track.timed(t)
        v = self.vehicles.get(sysid)
        if resolved and v is not None:
            self._feed_graphs(v, {"error": [r[1] for r in resolved]})

    def _estimate(self, v, m, now):
        payload = bytes(m.get_payload() or b"")
        track = self._truth(v.id)
        if v.est is not None:
            last = v.est.time_usec
            if m.time_usec < last:
                if last - m.time_usec > RESTART_US:
                    v.restarts += 1
                    v.est = None
                    if track is not None:
                        track.restart_estimates()
                else:
                    v.stale += 1
                    return
            elif m.time_usec == last and payload == v.est_payload:
                v.repeats += 1
                return
        v.est = m
        v.est_payload = payload
        c = m.pos_covariance
        v.ellipse = ellipse95(c[0], c[1], c[3])
        v.estimates += 1
        v.est_rate.add(now)
        resolved = track.estimate(m.time_usec, (m.x, m.y, m.z), c) if track is not None else []
        self._feed_graphs(v, {"nis": [m.nis], "ellipse": [v.ellipse[0] if v.ellipse else float("nan")],
                              "rate": [v.est_rate.rate(now)], "error": [r[1] for r in resolved]})

    # ---- idle ---------------------------------------------------------------------------------

    def idle_task(self):
        try:
            now = time.monotonic()
            if now - self._last_status >= 1.0:
                self._last_status = now
                self._hook_links()
                self.console.set_status("cooploc", self.summary(), row=5)
            period = max(0.1, float(self.settings_cooploc.status_period))
            if self.settings_cooploc.statusfile and now - self._last_file >= period:
                self._last_file = now
                self._write_statusfile()
            if self.settings_cooploc.map and now - self._last_map >= max(0.1, float(self.settings_cooploc.map_period)):
                self._last_map = now
                self._map_update()
        except Exception as e:
            self._error("idle_task", e)

    def summary(self):
        return "cooploc: %d vehicles, epoch %s, disagreements %d, heals %d" % (
            len(self.vehicles), "-" if self.epochs.last_epoch is None else self.epochs.last_epoch,
            self.epochs.disagreements, self.epochs.heals)

    def _write_statusfile(self):
        with open(self.settings_cooploc.statusfile, "a") as f:
            f.write("cooploc time=%.3f\n" % time.time())
            for line in self.status_lines():
                f.write(line + "\n")

    # ---- status -------------------------------------------------------------------------------

    def vehicle_line(self, v, now):
        e = v.est
        items = []
        if e is None:
            items += ["t_us=-"] + ["%s=-" % k for k in ("x", "y", "z", "vx", "vy", "vz", "yaw", "nis", "epoch",
                                                     "method", "participants", "ranges")]
        else:
            items.append("t_us=%d" % e.time_usec)
            items += ["%s=%s" % (k, fmt_float(getattr(e, k))) for k in ("x", "y", "z", "vx", "vy", "vz", "yaw", "nis")]
            items += ["epoch=%d" % e.epoch, "method=%s" % method_name(e.method),
                      "participants=%d" % e.participants, "ranges=%d" % e.ranges]
        if v.ellipse is None:
            items += ["semi_major_95=-", "semi_minor_95=-", "bearing_95_deg=-"]
        else:
            items += ["semi_major_95=%.3f" % v.ellipse[0], "semi_minor_95=%.3f" % v.ellipse[1],
                      "bearing_95_deg=%.1f" % v.ellipse[2]]
        c = self.epochs.node(v.id)
        items += [
            "loss_pct=%s" % v.loss_text(),
            "rate_hz=%.2f" % v.est_rate.rate(now),
            "bytes_per_s=%.0f" % v.bytes_rate.rate(now),
            "signed=%s" % v.signed_text(now),
            "disagreements=%d" % c["outvoted"],
            "heals=%d" % c["heals"],
            "reports=%d" % c["reports"],
            "partial=%d" % c["partial"],
            "failed=%d" % c["failed"],
            "store_wanted=%d" % c["store_wanted"],
            "store_fragments=%d" % v.store_fragments,
            "store_held=%d" % v.store_held,
            "state_fragments=%d" % v.state_fragments,
            "range_msgs=%d" % v.ranges,
            "range_bearings=%d" % v.range_bearings,
            "estimates=%d" % v.estimates,
            "acks=%d" % v.acks,
            "acks_refused=%d" % v.acks_refused,
            "restarts=%d" % v.restarts,
            "stale=%d" % v.stale,
            "rejected=%d" % v.rejected,
            "hb_type=%s" % ("-" if v.hb_type is None else v.hb_type),
            "hb_age_s=%s" % ("-" if v.hb_time is None else "%.1f" % (now - v.hb_time)),
        ]
        track = self.truths.get(v.id)
        latest = track.latest if track is not None else None
        items += [
            "error_m=%s" % ("-" if latest is None else repr(latest[1])),
            "nees=%s" % ("-" if latest is None or latest[2] is None else repr(latest[2])),
            "error_t_us=%s" % ("-" if latest is None else "%d" % latest[0]),
            "truth_samples=%d" % (0 if track is None else track.samples),
        ]
        return "cooploc vehicle %d %s" % (v.id, " ".join(items))

    def team_line(self):
        t = self.epochs
        return ("cooploc team vehicles=%d epoch=%s disagreements=%d heals=%d unhealed=%d epochs_held=%d "
                "duplicate_reports=%d vehicles_refused=%d rejected_unknown=%d undecoded=%d refresh_sent=%d "
                "origin=%r,%r,%r errors=%d last_rejected=%r last_error=%r" % (
                    len(self.vehicles), "-" if t.last_epoch is None else t.last_epoch, t.disagreements,
                    t.heals, int(t.unhealed_since is not None), t.epochs_held, t.repeats, self.vehicles_refused + t.dropped,
                    self.rejected_unknown, self.undecoded, self.refresh_sent, self.origin[0], self.origin[1],
                    self.origin[2], self.errors, self.last_rejected, self.last_error))

    def status_lines(self):
        now = time.monotonic()
        return [self.vehicle_line(self.vehicles[k], now) for k in sorted(self.vehicles)] + [self.team_line()]

    def _out(self, lines):
        """Prints (stdout: MAVProxy's console when headless) and, with a GUI console, writes
        there too."""
        for line in lines:
            print(line)
        console = self.mpstate.console
        if type(console).__name__ != "SimpleConsole":
            for line in lines:
                console.writeln(line)
        sys.stdout.flush()

    def team_table(self):
        now = time.monotonic()
        rows = [("id", "method", "epoch", "ellipse95 m (deg)", "error m", "NEES", "part", "loss %", "est/s", "B/s",
                 "signed", "disagree")]
        for k in sorted(self.vehicles):
            v = self.vehicles[k]
            e = v.est
            el = "-" if v.ellipse is None else "%.2fx%.2f (%.0f)" % v.ellipse
            track = self.truths.get(k)
            latest = track.latest if track is not None else None
            rows.append((str(k), "-" if e is None else method_name(e.method), "-" if e is None else str(e.epoch), el,
                         "-" if latest is None else "%.2f" % latest[1],
                         "-" if latest is None or latest[2] is None else "%.2f" % latest[2],
                         "-" if e is None else str(e.participants), v.loss_text(), "%.2f" % v.est_rate.rate(now),
                         "%.0f" % v.bytes_rate.rate(now), v.signed_text(now), str(self.epochs.node(k)["outvoted"])))
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
        lines.append(self.summary())
        return lines

    # ---- commands -----------------------------------------------------------------------------

    def cmd_cooploc(self, args):
        usage = "usage: cooploc <status|team|origin LAT LON ALT|refresh [ID]|graph nis|error|ellipse|rate ID|set>"
        if not args:
            print(usage)
            return
        try:
            cmd = args[0]
            if cmd == "status":
                self._out(self.status_lines())
            elif cmd == "team":
                self._out(self.team_table())
            elif cmd == "origin":
                self.cmd_origin(args[1:])
            elif cmd == "refresh":
                self.cmd_refresh(args[1:])
            elif cmd == "graph":
                self.cmd_graph(args[1:])
            elif cmd == "set":
                self.settings_cooploc.command(args[1:])
            else:
                print(usage)
        except Exception as e:
            self._error("command %s" % " ".join(args), e)

    def cmd_origin(self, args):
        if not args:
            print("cooploc origin %r %r %r" % self.origin)
            return
        try:
            lat, lon, alt = (float(a) for a in args[:3]) if len(args) >= 3 else (float(args[0]), float(args[1]), 0.0)
        except (ValueError, IndexError):
            print("usage: cooploc origin LAT LON ALT")
            return
        if not (-90.0 < lat < 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(alt)):
            print("cooploc origin: latitude in (-90, 90), longitude in [-180, 180]")
            return
        self.origin = (lat, lon, alt)
        for v in self.vehicles.values():
            v.map_drawn = False
        for track in self.truths.values():  # converted about the old origin: start over
            track.reset_truth()
        print("cooploc origin %r %r %r" % self.origin)

    def cmd_refresh(self, args):
        try:
            target = int(args[0]) if args else 0
        except ValueError:
            print("usage: cooploc refresh [ID]")
            return
        if not 0 <= target <= 255:
            print("cooploc refresh: ID in 0..255 (0: every node)")
            return
        links = 0
        for master in self.mpstate.mav_master:
            master.mav.command_long_send(target, NODE_COMPID, MAV_CMD_REQUEST_MESSAGE, 0,
                                         float(MSG_ESTIMATE), 0, 0, 0, 0, 0, 0)
            links += 1
        self.refresh_sent += 1
        print("cooploc refresh: REQUEST_MESSAGE COOPLOC_ESTIMATE to %s on %d links" % (
            "every node" if target == 0 else "node %d" % target, links))

    # ---- graphs -------------------------------------------------------------------------------

    GRAPH_KINDS = ("nis", "error", "ellipse", "rate")

    def _module_named(self, name):
        m = self.module(name)
        if m is not None:
            return m
        for (mod, _) in self.mpstate.modules:
            if getattr(mod, "name", None) == name:
                return mod
        return None

    def cmd_graph(self, args):
        if len(args) != 2 or args[0] not in self.GRAPH_KINDS:
            print("usage: cooploc graph nis|error|ellipse|rate ID (error: horizontal error against the truth, m; "
                  "ellipse: semi-major axis of the 95% ellipse, m)")
            return
        try:
            kind, vid = args[0], int(args[1])
        except ValueError:
            print("usage: cooploc graph nis|error|ellipse|rate ID")
            return
        graph = self._module_named("graph")
        if graph is None:
            print("cooploc graph: MAVProxy's graph module is not loaded: `module load graph` (needs wx and "
                  "matplotlib), then `cooploc graph %s %d` again" % (kind, vid))
            return
        # The graph module is single-vehicle (it only sees the target system's packets, on the
        # primary link): the module names the graph with a field no message provides, so that
        # the graph module leaves it alone, and feeds it each new value of that vehicle (error:
        # each estimate whose error against the truth becomes known).
        label = "cooploc.v%d.%s" % (vid, kind)
        before = list(getattr(graph, "graphs", []))
        self.mpstate.functions.process_stdin("graph %s" % label)
        created = [g for g in getattr(graph, "graphs", []) if g not in before]
        if created and hasattr(created[-1], "livegraph"):
            self._graphs.append((created[-1], vid, kind))
            print("cooploc graph: %s of vehicle %d" % (kind, vid))
            return
        if kind == "error":
            print("cooploc graph: this graph module takes no values from the module; the error against the "
                  "truth needs the truth (SIM_STATE) and is not a message field")
            return
        # Another graph module: its own expression, filtered for the vehicle (it updates only
        # while that vehicle is MAVProxy's target system).
        fields = {
            "nis": "COOPLOC_ESTIMATE.nis",
            "ellipse": "sqrt(%r*((COOPLOC_ESTIMATE.pos_covariance[0]+COOPLOC_ESTIMATE.pos_covariance[3])/2+"
                       "sqrt(((COOPLOC_ESTIMATE.pos_covariance[0]-COOPLOC_ESTIMATE.pos_covariance[3])/2)**2+"
                       "COOPLOC_ESTIMATE.pos_covariance[1]**2)))" % CHI2_2DOF_95,
            "rate": "COOPLOC_ESTIMATE.epoch",
        }
        self.mpstate.functions.process_stdin("graph %s{COOPLOC_ESTIMATE.platform==%d}" % (fields[kind], vid))
        print("cooploc graph: the graph module's own expression (updates while vehicle %d is the target system%s)"
              % (vid, "; rate shows the epoch instead" if kind == "rate" else ""))

    def _feed_graphs(self, v, values):
        """Adds ``values`` ({kind: [value, ...]}) of vehicle ``v`` to its graphs; forgets closed ones."""
        if not self._graphs:
            return
        alive = []
        for g, vid, kind in self._graphs:
            lg = getattr(g, "livegraph", None)
            if lg is None or not lg.is_alive():
                continue
            alive.append((g, vid, kind))
            if vid != v.id:
                continue
            for value in values.get(kind, ()):
                lg.add_values([value])
        self._graphs = alive

    # ---- map ----------------------------------------------------------------------------------

    def _map(self):
        mod = self.module("map")
        return getattr(mod, "map", None) if mod is not None else None

    def _map_update(self):
        slipmap = self._map()
        if slipmap is None:
            return
        mp_slipmap = slip_objects()
        for vid, v in self.vehicles.items():
            e = v.est
            if e is None:
                continue
            rgb = colour_rgb(vid)
            lat, lon, _ = _cooploc.ned_to_geo(e.x, e.y, e.z, self.origin)
            key = "cooploc_%d" % vid
            yaw_deg = math.degrees(e.yaw)
            if not v.map_drawn:
                slipmap.add_object(mp_slipmap.SlipIcon(key, (lat, lon), marker_image(rgb), layer="cooploc",
                                                       rotation=yaw_deg, label=str(vid), colour=rgb))
                v.map_drawn = True
            else:
                slipmap.set_position(key, (lat, lon), layer="cooploc", rotation=yaw_deg)
            if v.ellipse is not None:
                points = ellipse_polygon_latlon(e.x, e.y, v.ellipse, self.origin)
                try:
                    poly = mp_slipmap.SlipPolygon(key + "_ellipse", points, layer="cooploc", colour=rgb,
                                                  linewidth=2, showcircles=False)
                except TypeError:  # an older MAVProxy: no showcircles
                    poly = mp_slipmap.SlipPolygon(key + "_ellipse", points, layer="cooploc", colour=rgb, linewidth=2)
                slipmap.add_object(poly)

    def _map_clear(self):
        try:
            slipmap = self._map()
            if slipmap is None:
                return
            for vid in self.vehicles:
                slipmap.remove_object("cooploc_%d" % vid)
                slipmap.remove_object("cooploc_%d_ellipse" % vid)
        except Exception as e:
            self._error("map clear", e)


def slip_objects():
    """MAVProxy's map objects (SlipIcon, SlipPolygon, ...): mp_slipmap_util defines them and
    needs only OpenCV and numpy; mp_slipmap (which also needs wx) re-exports them."""
    try:
        from MAVProxy.modules.mavproxy_map import mp_slipmap_util
        return mp_slipmap_util
    except ImportError:
        from MAVProxy.modules.mavproxy_map import mp_slipmap
        return mp_slipmap


def marker_image(rgb, size=17):
    """A BGR image (numpy, black = transparent for SlipIcon) of a triangle pointing up (north at
    rotation 0) in colour ``rgb``."""
    import numpy as np
    img = np.zeros((size, size, 3), dtype=np.uint8)
    c = (size - 1) / 2.0
    for row in range(size):
        half = c * row / (size - 1)  # the apex at the top row
        lo, hi = int(round(c - half)), int(round(c + half))
        img[row, lo:hi + 1] = (rgb[2], rgb[1], rgb[0])
    return img


def init(mpstate):
    """MAVProxy's entry point."""
    return CooplocModule(mpstate)
