"""The edge agent: corrects its drive's angle with the coefficients it holds, ships one window of
additive statistics per interval, takes new coefficients from the service when they are safe.

Delivery is at-least-once: each window goes to the durable outbox before it is sent, and leaves it
only when the service's watermark (every seq up to N stored) passes it. The service drops
duplicates by (device, seq). So the agent can run with the service gone and catch up later.
"""

from __future__ import annotations

import json
import logging
import queue
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import msgspec
import numpy as np
import zenoh

from encoder_core.correction import BandedCorrection
from encoder_core.physics import REFERENCE_TEMP_C, band_of
from encoder_core.samples import InputError, Samples
from encoder_core.stats import normalisation_scale, rejected_by_reason, window_stats
from encoder_core.thermal import DieTemperature
from fleet_wire import keys
from fleet_wire import messages as wire

from .outbox import Outbox
from .sources import SampleSource

log = logging.getLogger("edge_agent")

# plausible bounds for a coefficient set: gains within 5x of the factory's, harmonics under 6°
MAX_GAIN_RATIO = 5.0
MAX_HARMONIC_RAD = 0.1
MAX_TERM_MOVE = 0.5  # offsets (w2, w4) and the axis terms (w5, zero) from the factory's: half the radius, ~29°


@dataclass
class AgentCounters:
    windows: int = 0
    unsent_windows: int = 0  # windows the wire cannot carry (no usable sample) or the outbox could not keep
    outbox_errors: int = 0  # steps the outbox failed in (its disk full or failing): the agent went on
    resent: int = 0
    applied: list[int] = field(default_factory=list)
    refused: list[tuple[int, str]] = field(default_factory=list)
    offline_syncs: int = 0  # watermark queries nobody answered (or only replies refused below): the service was away
    refused_watermarks: dict[str, int] = field(default_factory=dict)  # watermark replies refused, by reason
    bad_signatures: int = 0  # sets refused as unsigned or not signed by the service's key
    bad_messages: int = 0  # every payload on the coefficients key refused, whatever the reason


def temperature_range(lo: float, hi: float) -> tuple[float, float]:
    """A drive's thermistor rating as the agent reads temperatures in it (`agent --temp-range LO,HI`): LO below HI,
    both within the wire's range, or InputError."""
    if not (wire.TEMP_MIN_C <= lo < hi <= wire.TEMP_MAX_C):
        raise InputError(
            f"temperature range {lo:g},{hi:g} °C: LO must be below HI, both within "
            f"{wire.TEMP_MIN_C:g},{wire.TEMP_MAX_C:g} °C (the wire's)"
        )
    return float(lo), float(hi)


class EdgeAgent:
    def __init__(
        self,
        device: str,
        source: SampleSource,
        session: zenoh.Session,
        outbox: Outbox,
        factory: BandedCorrection,
        *,
        window_s: float = 60.0,
        resend_after_s: float = 2.0,
        query_timeout_s: float = 1.0,
        verifier=None,
        clock: Callable[[], float] = time.monotonic,
        temp_range_c: tuple[float, float] = (wire.TEMP_MIN_C, wire.TEMP_MAX_C),
    ):
        # readings outside it are a broken sensor's (readable_temperatures): the drive's own rating, when given
        self.temp_range_c = temperature_range(*temp_range_c)
        self.device = device
        self.source = source
        self.session = session
        self.outbox = outbox
        self.factory = factory
        self.correction = factory
        self.version = 0
        self.window_s = window_s
        self.resend_after_s = resend_after_s
        self.query_timeout_s = query_timeout_s
        self.verifier = verifier  # fleet_wire.security.SetVerifier: sets and watermark replies must be the service's
        self.clock = clock  # paces resends only: nothing the agent keeps depends on it
        self.time_offset: float | None = None  # added to the drive clock so it never runs back (checked every block)
        self.resume_end: float | None = None  # the service's last window end, when it is past the outbox's
        # the newest window issued ends here (drive clock), as the outbox keeps it: read once, then kept with every
        # window, so that a block is continued and corrected without a read of an outbox that may be failing
        self.issued_end: float | None = outbox.last_window_end()
        self.keys = {suffix: keys.key(device, suffix) for suffix in keys.SUFFIXES}
        self.seq = outbox.last_seq()
        # the windows after start_seq were numbered with no word from the service (by this process, or by one
        # that stopped before the service answered): they are not sent until it has said where it stands
        self.start_seq = outbox.unresumed_after()
        self.resumed = False
        self.counters = AgentCounters()
        self.inbox: queue.Queue[bytes] = queue.Queue()
        self.pending_ack: int | None = None
        self.service_has_set = False  # until the service answers our question for a set (ask_for_set)
        self.watermark = 0  # the service's contiguous watermark, as its last reply said
        # the service has retired this drive (its last reply said so): its windows are kept, not sent, until it is
        # reinstated (every one sent was refused, and the outbox resent every few seconds)
        self.retired = False
        # the statistics' normalisation stays fixed for the device's whole life: windows must merge
        self.scale = normalisation_scale(factory)
        self.die = DieTemperature()  # the die's temperature, lagged from what the drive reports (thermal_lag_s)
        self._declared: list = []
        saved = outbox.saved_coefficients()
        if saved is not None:
            self.on_coefficients(saved, acknowledge=False)  # resume with what we ran before a restart

    # --- lifecycle ---------------------------------------------------------------------------------

    def start(self) -> None:
        self._declared.append(self.session.liveliness().declare_token(self.keys["alive"]))
        self._declared.append(
            self.session.declare_subscriber(
                self.keys["coefficients"], lambda sample: self.inbox.put(sample.payload.to_bytes())
            )
        )
        self.resume_after_service()
        self.ask_for_set()

    def resume_after_service(self, reply: bytes | None = None) -> None:
        """An agent whose outbox was lost (a new disk, a container without its volume) would number its windows
        from 1 again and start its drive clock at 0: the service, which has those seqs, refuses every window as a
        seq conflict until the count passes its own. Where the service has stored more of us than the outbox
        knew, go on after its last window, seq and drive time. Asked at start; when the service is away then, the
        first watermark reply answers it (`reply`), and the windows numbered meanwhile, kept back until then,
        are moved after the service's."""
        if reply is None:
            replies = self._ask_received()
            if not replies:
                return  # no service yet: the outbox is all we know (sync asks again)
            reply = replies[0]
        try:
            contiguous, _ = wire.parse_watermark_reply(reply, self.device)
        except wire.WireError as exc:
            log.warning("%s: %s", self.device, exc)
            return
        self._heard_retired(reply)  # at start, before the first window (restarted, a retired drive sent it, refused)
        try:
            last = wire.parse_resume_point(reply, self.device)
        except wire.WireError as exc:  # a watermark all the same: go on as with a service that names no resume point
            log.warning("%s: %s", self.device, exc)
            last = None
        if last is None or last[0] <= self.start_seq:
            self.outbox.resumed()
            self.resumed = True
            return
        # seqs from the service's contiguous watermark, time after its newest window: a gap (windows lost with
        # the outbox) is filled by new ones, or the watermark and the monitor would wait at it forever; a new
        # window that lands on a seq the service has past the gap is refused as a seq conflict
        first = max(self.start_seq, contiguous)
        log.warning(
            "%s: the service has windows up to seq %d (contiguous to %d, drive clock %.1f s), the outbox only "
            "up to %d: going on from seq %d (outbox lost or replaced?)",
            self.device, last[0], contiguous, last[1], self.start_seq, first + 1,
        )  # fmt: skip
        self.resume_end = last[1]
        shift_t = [0.0]
        moved_end: list[float] = []  # the newest moved window's end: the outbox's last window end after the move

        def moved(rows: list[tuple[int, bytes]]) -> list[tuple[int, bytes, float]]:
            # numbered on from `first` (windows a full outbox dropped leave no gap), after the service's newest
            wins = [wire.decode_window(payload, key_device=self.device) for _, payload in rows]
            shift_t[0] = max(0.0, last[1] - wins[0].window_start + RESUME_GAP_S)
            wins = [
                msgspec.structs.replace(
                    w, seq=first + i, window_start=w.window_start + shift_t[0], window_end=w.window_end + shift_t[0]
                )
                for i, w in enumerate(wins, start=1)
            ]
            moved_end.append(max(w.window_end for w in wins))
            return [(w.seq, wire.encode_window(w), w.window_end) for w in wins]

        moved_count = self.outbox.resumed(moved)
        self.seq = first + moved_count
        if moved_count:
            self.issued_end = moved_end[-1]
            log.warning(
                "%s: %d window(s) numbered while the service was away moved after its own", self.device, moved_count
            )
        if moved_count and self.time_offset is not None:  # this process's windows to come follow the moved ones
            self.time_offset += shift_t[0]
        else:  # set at the next block, after the newest of the moved windows (the outbox's) and the service's
            self.time_offset = None
        self.resumed = True

    def ask_for_set(self) -> None:
        """Ask the service for our set; when it has none (or is not there), tell it what the factory wrote.
        Repeated at each sync until the service answers with a set: an agent that started with no router
        still announces its factory set once one appears."""
        replies = self._get(self.keys["coefficients"]) or []
        self.service_has_set = any(self.trusted(p) or self._is_own_factory(p) for p in replies)
        if not self.service_has_set:
            self.put(self.keys["factory"], wire.encode("coefficients", self.factory_message()))
        for payload in replies:
            self.inbox.put(payload)

    def close(self) -> None:
        for entity in reversed(self._declared):
            entity.undeclare()
        self._declared.clear()

    def run(self, *, real_time_factor: float = 0.0, stop: threading.Event | None = None) -> AgentCounters:
        """Process the source to its end (or until `stop` is set). real_time_factor > 0 paces the drive's
        clock at that many times real time; 0 runs as fast as the machine can."""
        started, drive_started = time.monotonic(), self.source.now
        while stop is None or not stop.is_set():
            try:
                if not self.step():
                    break
            except sqlite3.Error as exc:  # the outbox's disk (full, failing): logged, and the drive keeps its angle
                log.warning("%s: the outbox failed: %s", self.device, exc)
                self.counters.outbox_errors += 1
            if real_time_factor > 0:
                # by the drive's clock, not the windows made: a replayed recording's stretch with no sample (the
                # logger stopped for an hour) makes no window and still takes its time
                ahead = (self.source.now - drive_started) / real_time_factor - (time.monotonic() - started)
                if ahead > 0:
                    time.sleep(ahead)
        if stop is None or not stop.is_set():
            self.drain()
        return self.counters

    # --- one window --------------------------------------------------------------------------------

    def step(self) -> bool:
        self.apply_inbox()
        block = self.source.read(self.window_s)
        if block is None:
            return False
        if len(block) == 0:
            return True
        # at every block, not only the first: a drive clock that steps back under a running agent (NTP, a controller
        # restarted) made windows the service refuses as clock_backwards, held until the clock came past again
        ends = [e for e in (self.issued_end, self.resume_end) if e is not None]
        offset = self.time_offset or 0.0
        shift = continued_clock(block.t + offset, max(ends, default=None))
        if shift > 0 and self.time_offset is not None:
            log.warning(
                "%s: the drive clock went back %.1f s: its windows go on after the last one (%.1f s)",
                self.device, max(ends) - float(block.t[0]) - offset, max(ends),
            )  # fmt: skip
        if np.isfinite(shift):
            self.time_offset = offset + shift
        block = self.readable_temperatures(block)
        block = self.at_die_temperature(block)  # the correction and the window's temperatures: the die's
        self.correct(block)  # the product: the drive's corrected angle (handed to its controller)
        usable, by_reason = rejected_by_reason(block)  # spikes and clipping counted per reason, for the monitor
        quality = self.angle_quality_deg(block, usable)
        if self.pending_ack is not None:
            self.send_ack(self.pending_ack, "applied", quality)
            self.pending_ack = None
        stats = window_stats(block, self.scale, usable)
        start, end = float(block.t[0]) + self.time_offset, float(block.t[-1]) + self.time_offset
        try:
            msg = wire.window_message(
                device=self.device,
                seq=self.seq + 1,
                window_start=start,
                window_end=end,
                stats=stats,
                coefficients_version=self.version,
                angle_quality_deg=quality,
                temp_rate_c_per_s=temp_rate(block),
                rejected_by_reason=by_reason,
            )
            payload = wire.encode("window", msg)
        except wire.WireError as exc:
            # not sent, and no seq used: the service's watermark needs seqs without gaps. A window of no usable
            # sample has no temperature and so no band, which the schema requires; carrying it would mean a
            # schema and store change, so the monitor does not see this window's rejections (logged here)
            log.warning(
                "%s: window %.1f-%.1f s (drive clock) not sent, %d of %d samples rejected %s: %s",
                self.device,
                start,
                end,
                stats.rejected,
                len(block),
                by_reason,
                exc,
            )
            self.counters.unsent_windows += 1
            self.sync()  # what the outbox holds is still resent
            return True
        try:
            self.outbox.add(self.seq + 1, payload, window_end=msg["window_end"])
        except sqlite3.Error as exc:
            # the outbox cannot keep it (its disk is full): not sent and no seq used, as above; the drive's angle was
            # corrected all the same, and the agent goes on (it stopped here, and the correction with it)
            log.warning("%s: window %.1f-%.1f s not kept, the outbox refused it: %s", self.device, start, end, exc)
            self.counters.unsent_windows += 1
            return True
        self.seq += 1
        self.issued_end = msg["window_end"]
        if self.resumed and not self.retired:  # before the service has said where it stands, seq and time may move
            self.put(self.keys["stats"], payload)
            self.outbox.mark_sent([("window", self.seq)], self.clock())
        self.counters.windows += 1
        self.sync()
        return True

    def readable_temperatures(self, block: Samples) -> Samples:
        """The block with every temperature outside the agent's range read as NaN: the wire's (below absolute zero,
        above 300 °C), or the drive's rating when given (`--temp-range`). Such a reading is an open or shorted
        thermistor's or a converter's garbage, and NaN is what it tells: its sample is rejected as non_finite, its
        angle corrected at the die's last good estimate, and the estimate does not move. Summed into the window, one
        such reading took its temperature past the range and the wire refused the whole window."""
        temp = block.temp_c
        if temp is None:
            return block
        lo, hi = self.temp_range_c
        broken = (temp < lo) | (temp > hi)
        return replace(block, temp_c=np.where(broken, np.nan, temp)) if broken.any() else block

    def at_die_temperature(self, block: Samples) -> Samples:
        """The block with its temperatures replaced by the die estimate of the set the agent runs."""
        if block.temp_c is None:
            return block
        return replace(block, temp_c=self.die(block.t, block.temp_c, self.correction.thermal_lag_s))

    def correct(self, block: Samples) -> np.ndarray:
        """The corrected angle of every sample. A temperature that reads NaN is corrected at the die's last finite
        estimate (the interpolation across bands would make the angle handed to the drive NaN); the sample itself
        stays rejected from the statistics."""
        temp = block.temp_c
        if temp is not None and not np.all(np.isfinite(temp)):
            # before any finite reading (a channel dead from the start) at the bench's temperature
            known = self.die.last[2] if self.die.last is not None else REFERENCE_TEMP_C
            temp = np.where(np.isfinite(temp), temp, known)
        return self.correction.angle(block.d, block.q, temp)

    def angle_quality_deg(self, block: Samples, usable: np.ndarray) -> float:
        """Reference-free: how far the corrected signals are from a circle (radius ripple, as an angle)."""
        if usable.sum() < 8:
            return 0.0
        r = self.correction.radius(
            block.d[usable], block.q[usable], None if block.temp_c is None else block.temp_c[usable]
        )
        return float(np.degrees(np.std(r) / np.mean(r)))

    # --- delivery ----------------------------------------------------------------------------------

    def sync(self) -> bool:
        """Ask the service how far it has stored us; forget what it has, resend what it lacks (windows and
        acks alike)."""
        replies = self._ask_received()
        if not replies:
            self.counters.offline_syncs += 1
            return False
        try:
            watermark, acked = wire.parse_watermark_reply(replies[0], self.device)
        except wire.WireError as exc:
            log.warning("%s: %s", self.device, exc)
            return False
        if not self.resumed:
            self.resume_after_service(replies[0])
            if not self.resumed:
                return False
        if not self.service_has_set:
            self.ask_for_set()
        if self.version > acked and self.pending_ack is None and self.version not in self.outbox.pending_acks():
            # the set this agent runs was applied and never acknowledged (the process ended before its next block,
            # and a restart resumes it without a word): the service clears a step's alarm on that ack
            self.pending_ack = self.version
        self.watermark = watermark
        self.outbox.confirm_through(watermark, acked)
        if self._heard_retired(replies[0]):
            return True
        due = self.outbox.due(self.clock(), self.resend_after_s)
        for kind, _, payload in due:
            self.put(self.keys["ack" if kind == "ack" else "stats"], payload)
        if due:
            self.outbox.mark_sent([(kind, ident) for kind, ident, _ in due], self.clock())
            self.counters.resent += len(due)
        return True

    def _heard_retired(self, reply: bytes) -> bool:
        """Whether the (checked) watermark reply says the service has retired this drive; said once it changes."""
        retired = wire.says_retired(reply)
        if retired != self.retired:
            if retired:
                log.warning("%s: the service has retired this drive: its windows are kept here, not sent", self.device)
            else:
                log.warning("%s: the service has reinstated this drive: sending its windows again", self.device)
            self.retired = retired
        return retired

    def drain(self, timeout_s: float = 20.0) -> bool:
        """At the end: keep syncing until the service has every window (or time runs out)."""
        deadline = time.monotonic() + timeout_s
        while (len(self.outbox) or self.outbox.pending_acks()) and not self.retired and time.monotonic() < deadline:
            self.apply_inbox()
            time.sleep(0.1 if self.sync() else 0.2)
        self.apply_inbox()
        return len(self.outbox) == 0 and not self.outbox.pending_acks()

    def put(self, key: str, payload: bytes) -> None:
        # windows are few and must arrive: wait for room rather than drop (Zenoh's default for put)
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def _ask_received(self) -> list[bytes] | None:
        """The watermark question. Once the outbox has dropped windows (full while the service was away) and the
        service's watermark waits below what it still holds, it says that what the service lacks below is gone:
        otherwise the watermark, and the drift monitor reading up to it, would wait at the first of them for ever.
        Not before the windows' seqs are settled (`resumed`: held windows may still be moved).

        With security on, the question carries a fresh nonce, and only replies the service signed for it are
        returned: a forged one (whoever else can answer: a meshed router's stolen key), an old one replayed (after
        an outbox lost and renumbered, its higher watermark would drop windows never stored) or an unsigned one (a
        service before signed replies) is logged and counted, and the outbox keeps everything, as with no reply."""
        gone = None
        if self.resumed and self.outbox.dropped:
            held_from = self.outbox.held_from()
            if held_from > self.watermark + 1:
                gone = held_from
        nonce = wire.new_nonce() if self.verifier is not None else None
        replies = self._get(self.keys["received"], payload=wire.received_query(self.device, gone, nonce))
        if nonce is None or not replies:
            return replies
        trusted = []
        for reply in replies:
            try:
                wire.parse_watermark_reply(reply, self.device, verifier=self.verifier, nonce=nonce)
            except wire.WireError as exc:
                self.counters.refused_watermarks[exc.reason] = self.counters.refused_watermarks.get(exc.reason, 0) + 1
                hint = " (a service before signed watermark replies? upgrade it)" if exc.reason == "unsigned" else ""
                log.warning(
                    "%s: refused a watermark reply, the outbox keeps its windows (asked again later): %s%s",
                    self.device, exc, hint,
                )  # fmt: skip
                continue
            trusted.append(reply)
        return trusted

    def _get(self, key: str, payload: bytes | None = None) -> list[bytes] | None:
        try:
            # every reply, not Zenoh's default of the latest per key: a forged reply on the same key would hide the
            # genuine one, which the caller then could not pick out
            replies = self.session.get(
                key, payload=payload, timeout=self.query_timeout_s, consolidation=zenoh.ConsolidationMode.NONE
            )
            return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]
        except zenoh.ZError as exc:  # the session itself failed
            log.warning("%s: get %s failed: %s", self.device, key, exc)
            return None

    # --- coefficients ------------------------------------------------------------------------------

    def apply_inbox(self) -> None:
        while True:
            try:
                payload = self.inbox.get_nowait()
            except queue.Empty:
                return
            self.on_coefficients(payload)

    def trusted(self, payload: bytes) -> bool:
        """A set that decodes for this device and carries the service's signature (when one is required)."""
        try:
            msg = wire.decode("coefficients", payload, key_device=self.device)
            if self.verifier is not None:
                self.verifier.verify(msg)
        except wire.WireError:
            return False
        return True

    def _is_own_factory(self, payload: bytes) -> bool:
        """The service's copy of our own factory set (version 0, which it keeps unsigned, as announced): it has our
        set. Only our own bands count, so a reply nobody signed can stop nothing but a repeat of the same set."""
        try:
            msg = wire.decode("coefficients", payload, key_device=self.device)
        except wire.WireError:
            return False
        mine = json.loads(json.dumps(self.factory_message()))  # as the wire carries it
        return msg["version"] == 0 and msg["basis"] == "factory" and msg["bands"] == mine["bands"]

    def on_coefficients(self, payload: bytes, *, acknowledge: bool = True) -> None:
        signed = True
        try:
            msg = wire.decode("coefficients", payload, key_device=self.device)
            if self.verifier is not None and msg["version"] > 0:
                try:
                    self.verifier.verify(msg)  # before anything else: an unsigned set is not even compared
                except wire.WireError:
                    self.counters.bad_signatures += 1
                    signed = False
                    raise
            if msg["version"] <= self.version:
                return  # an old or repeated set: nothing to do, nothing to say
            candidate = BandedCorrection.from_dict(msg)  # the bands, and the die lag to read them at
            check_plausible(candidate, self.factory)
        except (wire.WireError, InputError) as exc:
            self.counters.bad_messages += 1
            version = _version_of(payload)
            log.warning("%s: refused coefficient set %s: %s", self.device, version, exc)
            if acknowledge and version is not None and version > self.version:
                self.counters.refused.append((version, str(exc)))
                # a set the service signed is answered durably; one it did not sign is not its set, and the
                # service will refuse the answer (forged_ack): said once, not resent forever
                self.send_ack(version, "rejected", None, reason=str(exc), durable=signed)
            return
        self.correction, self.version = candidate, int(msg["version"])
        self.outbox.save_coefficients(payload)
        if acknowledge:
            self.counters.applied.append(self.version)
            self.pending_ack = self.version  # acknowledged with the quality seen on the next block

    def send_ack(
        self, version: int, status: str, quality: float | None, *, reason: str | None = None, durable: bool = True
    ) -> None:
        msg = wire.ack_message(
            device=self.device,
            version=version,
            status=status,
            angle_quality_deg=quality,
            at=float(self.source.now) + (self.time_offset or 0.0),
            reason=reason,
        )
        payload = wire.encode("ack", msg)
        if durable:
            self.outbox.add_ack(version, payload)  # resent until the watermark confirms it, like a window
        if self.retired:  # the service stores nothing of the drive: kept (durable), and sent once it is reinstated
            return
        if durable:
            self.outbox.mark_sent([("ack", version)], self.clock())
        self.put(self.keys["ack"], payload)

    def factory_message(self) -> dict:
        return factory_message(self.device, self.factory)


def factory_message(device: str, factory: BandedCorrection) -> dict:
    """What the factory wrote into the drive, as coefficient set version 0."""
    bands = [
        wire.band_entry(
            band_of(REFERENCE_TEMP_C if b.temp_c is None else b.temp_c),
            b.to_dict(),
            {"samples": 0, "residual_rms_rad": 0.0, "radius_ripple_rad": 0.0},
        )
        for b in factory.bands
    ]
    return wire.coefficients_message(device=device, version=0, created_at=0.0, basis="factory", bands=bands)


def check_plausible(candidate: BandedCorrection, factory: BandedCorrection) -> None:
    ref = factory.bands[0]
    for band in candidate.bands:
        values = [band.w1, band.w2, band.w3, band.w4, band.w5, band.zero_offset_rad]
        values += [v for ab in band.harmonics.values() for v in ab]
        if not np.all(np.isfinite(values)):
            raise InputError(f"band at {band.temp_c} °C has a non-finite coefficient")
        for name, w, w_ref in (("w1", band.w1, ref.w1), ("w3", band.w3, ref.w3)):
            ratio = w / w_ref
            if not (1 / MAX_GAIN_RATIO < ratio < MAX_GAIN_RATIO):
                raise InputError(f"band at {band.temp_c} °C: {name} = {w:.4g} is {ratio:.3g}x the factory's")
        for name, w, w_ref in (
            ("w2", band.w2, ref.w2),
            ("w4", band.w4, ref.w4),
            ("w5", band.w5, ref.w5),
            ("zero_offset_rad", band.zero_offset_rad, ref.zero_offset_rad),
        ):
            if abs(w - w_ref) > MAX_TERM_MOVE:  # in the circle's own units: a move of half its radius is no drift
                raise InputError(f"band at {band.temp_c} °C: {name} = {w:.4g} is {w - w_ref:+.3g} from the factory's")
        for m, (a, b) in band.harmonics.items():
            if np.hypot(a, b) > MAX_HARMONIC_RAD:
                raise InputError(f"band at {band.temp_c} °C: harmonic {m} of {np.hypot(a, b):.3g} rad is implausible")


def continued_clock(t: np.ndarray, last_window_end: float | None) -> float:
    """What to add to the drive clock so this run's windows start after the last one this agent ever sent:
    a drive that restarts its clock at 0 would otherwise send stretches of drive time the service has."""
    if last_window_end is None or len(t) == 0 or t[0] > last_window_end:
        return 0.0
    step = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    return last_window_end - float(t[0]) + step


def temp_rate(block: Samples) -> float:
    """The window's temperature slope, °C/s, from its finite readings (a NaN one is rejected, not fitted)."""
    if block.temp_c is None:
        return 0.0
    ok = np.isfinite(block.temp_c) & np.isfinite(block.t)
    t, temp = block.t[ok], block.temp_c[ok]
    if t.size < 2 or t[-1] == t[0]:
        return 0.0
    dt = t - t.mean()  # the least-squares line's slope in closed form (np.polyfit's SVD cost ~0.3 ms a window)
    return float(np.dot(dt, temp - temp.mean()) / np.dot(dt, dt))


RESUME_GAP_S = 1e-3  # drive time between the service's newest window and the first one renumbered after it
MAX_VERSION = 2**53 - 1  # the schemas' bound: an ack can carry no larger version


def _version_of(payload: bytes) -> int | None:
    """The version a refused set claims, if an ack could name it (a whole number within the schema's range)."""
    try:
        v = json.loads(payload).get("version")
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v == int(v)
        return int(v) if ok and 0 <= v <= MAX_VERSION else None
    except (ValueError, AttributeError, TypeError, RecursionError):
        return None
