"""Several service processes, one fleet (issue 13).

Every device belongs to one of `keys.PARTITIONS` partitions (a stable hash of its id, in its keys). Each
running service process declares a liveliness token `encoders/_services/<member>`, watches the others', and
serves the partitions that rendezvous hashing gives it among the live members: it subscribes to those
partitions' keys only, so it receives only its devices' windows, acks and tokens, and it refits and monitors
only its devices. A process that joins takes about 1/N of the partitions from the others; one that dies
leaves its partitions to the rest. Every process answers REST for the whole fleet from the shared database.

Handing a partition over loses and doubles nothing: a partition's writer holds a PostgreSQL advisory lock
for it, taken before its subscriptions are declared and let go only after they are undeclared and the
batch being written is committed, so two processes never write one device's history at once (the store's
in-memory band sums stay true). A window sent while nobody serves its partition stays in the agent's outbox
(the watermark never covered it) and is sent again; one that reaches both is stored once (unique device, seq).
The refit and monitor passes work on each device under its partition's hand-over guard (`Partitions.serving`):
the lock is let go of only once the device work in hand on the partition has ended, and none starts meanwhile,
so two processes never refit or monitor one device at once either (two sets for one refusal, a state written
over the new owner's).
"""

from __future__ import annotations

import hashlib
import logging
import re
import threading
from collections import Counter
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import zenoh

from fleet_wire import keys

log = logging.getLogger("service.cluster")
MEMBER_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
REBALANCE_S = 0.5  # how often a partition another process still holds is tried again


def owner(part: int, members: Iterable[str]) -> str:
    """The member that serves `part`: highest hash of (member, part). When a member joins or leaves, only the
    partitions it takes or leaves move."""
    return max(members, key=lambda m: (hashlib.blake2b(f"{m}/{part}".encode(), digest_size=8).digest(), m))


def shares(member: str, members: Iterable[str]) -> set[int]:
    """The partitions `member` serves among `members` (itself included)."""
    everyone = set(members) | {member}
    return {p for p in range(keys.PARTITIONS) if owner(p, everyone) == member}


class Partitions:
    """The partitions this process serves and the Zenoh entities that serve them, kept in step with the live
    service processes. Standalone (member None, the embedded default): every partition, one wildcard entity per key.
    `lock` is held by the writer while it stores a batch and by a hand-over, so neither cuts into the other; work
    on one device (a refit, the monitor) holds its partition's guard (`serving`), which a hand-over waits for."""

    def __init__(self, service, member: str | None):
        if member is not None and not MEMBER_RE.fullmatch(member):  # match() let a name end in a newline
            raise ValueError(f"service member name {member!r} does not match {MEMBER_RE.pattern}")
        self.service = service
        self.member = member
        self.lock = threading.Lock()
        self.held: frozenset[int] = frozenset()
        self._entities: dict[int | None, list] = {}
        self._members: set[str] = set()
        self._members_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cluster_entities: list = []
        # the hand-over guard: device work in hand per partition, and the partitions being let go of (no new work)
        self._work = threading.Condition()
        self._working: Counter[int] = Counter()
        self._handing: set[int] = set()

    @property
    def standalone(self) -> bool:
        return self.member is None

    def serves(self, device: str) -> bool:
        return self.standalone or keys.partition(device) in self.held

    @contextmanager
    def serving(self, device: str) -> Iterator[bool]:
        """Work on one device (a refit, the monitor's feed, an alarm's consequences): True while this process serves
        it, and its partition is not let go of until the block ends; False (leave the device alone: its new owner
        looks at it) when it serves it no more or is handing it over. It never waits; a thread inside the block must
        not wait for a hand-over (rebalance, which waits for the block)."""
        if self.standalone:
            yield True
            return
        part = keys.partition(device)
        with self._work:
            mine = part in self.held and part not in self._handing
            if mine:
                self._working[part] += 1
        try:
            yield mine
        finally:
            if mine:
                with self._work:
                    self._working[part] -= 1
                    self._work.notify_all()

    @contextmanager
    def _handing_over(self, part: int) -> Iterator[None]:
        """A partition let go of: no device work starts on it, and the block begins once the work in hand has ended.
        Taken before `lock` (the writer holds `lock`, never this guard), never inside a `serving` block."""
        with self._work:
            self._handing.add(part)
            self._work.wait_for(lambda: self._working[part] == 0)
        try:
            yield
        finally:
            with self._work:
                self._handing.discard(part)

    def leads(self) -> bool:
        """The one process that steps staged rollouts: the one serving partition 0."""
        return self.standalone or 0 in self.held

    def members(self) -> list[str]:
        with self._members_lock:
            return sorted(self._members | ({self.member} if self.member else set()))

    # --- lifecycle ---------------------------------------------------------------------------------

    def start(self) -> None:
        if self.standalone:
            self._entities[None] = self.service._declare_partition(None)
            self.held = frozenset(range(keys.PARTITIONS))
            return
        liveliness = self.service.session.liveliness()
        self._cluster_entities = [
            liveliness.declare_token(f"{keys.SERVICES}/{self.member}"),
            liveliness.declare_subscriber(f"{keys.SERVICES}/*", self._on_member, history=True),
        ]
        self._thread = threading.Thread(target=self._loop, name="partitions", daemon=True)
        self._thread.start()

    def stop_receiving(self) -> None:
        """Stop following the members and undeclare every partition's entities (the first step of a stop)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
        for part in list(self._entities):
            self._undeclare(part)

    def release(self) -> None:
        """Let go of every partition, then leave the members (once the last batch is written)."""
        with self.lock:
            for part in self.held if not self.standalone else ():
                self.service.store.release_partition(part)
            self.held = frozenset()
        for entity in reversed(self._cluster_entities):
            entity.undeclare()
        self._cluster_entities.clear()

    # --- membership ---------------------------------------------------------------------------------

    def _on_member(self, sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        joined = sample.kind == zenoh.SampleKind.PUT
        with self._members_lock:
            if joined:
                self._members.add(name)
            else:
                self._members.discard(name)
        log.info("service member %s %s", name, "joined" if joined else "left")
        self._wake.set()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            try:
                self.rebalance()
            except Exception:  # the database or the session: logged, tried again on the next pass
                log.exception("rebalancing partitions failed")
            self._wake.wait(REBALANCE_S)

    def connection_renewed(self) -> None:
        """The database session was lost and opened again: its advisory locks went with it, so this process holds
        no partition until it has taken each one again (the next rebalance). Called with `lock` free."""
        if self.standalone:
            return
        with self.lock:
            lost, self.held = self.held, frozenset()
        self.service.forget_partitions(set(lost))
        log.warning("database session renewed: the partitions' locks were lost and are taken again")
        self._wake.set()

    def rebalance(self) -> None:
        """Let go of the partitions another member now serves, then take the ones this member now serves."""
        self.service._renew_if_lost()
        for part in [p for p in self._entities if p not in self.held]:
            self._undeclare(part)  # held no more (a lost session): stop receiving until it is taken again
        want = shares(self.member, self.members())
        lost = sorted(self.held - want)
        for part in lost:
            self._undeclare(part)
            # after the device work in hand on it (a refit, a monitor page: the next owner would do it again, at the
            # same time) and the batch in hand: what is still queued for it is dropped, and sent again
            with self._handing_over(part), self.lock:
                self.held = self.held - {part}
                self.service.store.release_partition(part)
        if lost:
            self.service.forget_partitions(set(lost))
            log.info("partitions released: %s", " ".join(map(keys.partition_chunk, lost)))
        # a partition whose last holder has not let go yet (or whose connection is not gone yet) waits a pass
        gained = {part for part in sorted(want - self.held) if self.service.store.claim_partition(part)}
        if gained:
            self.service.forget_partitions(gained)  # whatever this process knew of them, another may have changed
            with self.lock:
                self.held = self.held | gained
            for part in sorted(gained):
                self._entities[part] = self.service._declare_partition(part)
            self.service.adopt_partitions(gained)
            log.info("partitions taken: %s", " ".join(map(keys.partition_chunk, sorted(gained))))

    def _undeclare(self, part: int | None) -> None:
        for entity in reversed(self._entities.pop(part, [])):
            entity.undeclare()
