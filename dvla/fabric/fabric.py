"""`Fabric`: the two Zenoh sessions of one process and everything sent or received through them.

The **data** session carries trajectory chunks only (BLOCK congestion control: none vanish in
the network); the **ctrl** session, on a link of its own so a flooded data plane cannot delay
it, carries weights, commands, status, eval results and liveliness.

Every message, query and reply is a signed envelope (:mod:`dvla.fabric.signing`; replies bound
to their query's nonce). Zenoh callbacks hand messages to a bounded :class:`Inbox` and never
block for long; everything is counted. Usable without any dvla configuration: pass two plain
`zenoh.Config` objects (docs/embedding.md).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from typing import Any, Callable

import zenoh

from .accounting import UNAUTHENTICATED, Accounting  # noqa: F401 (re-exported: fabric.UNAUTHENTICATED)
from .codec import CodecError, decode, encode, encode_into
from .identity import Identity, authorize
from .keys import KeySpace
from .signing import SignatureError, Signer, Verifier, nonce_of
from .zconfig import MAX_MESSAGE_SIZE_KEY

log = logging.getLogger("dvla.fabric")

DATA, CTRL = "data", "ctrl"
#: Zenoh's limit on one session handshake (ms)
OPEN_TIMEOUT_KEY = "transport/unicast/open_timeout"


#: priority of commands, status and eval results: above everything else on the ctrl link
PRIO_CTRL = zenoh.Priority.INTERACTIVE_HIGH
#: weights: urgent but bulky; below commands so a `stop` overtakes a weight transfer
PRIO_WEIGHTS = zenoh.Priority.DATA_HIGH
#: trajectories
PRIO_DATA = zenoh.Priority.DATA


class Inbox:
    """Bounded hand-off from a Zenoh callback to a lane.

    The callback waits at most `block_s` for space (backpressure through Zenoh's BLOCK
    congestion control), then drops and counts the message: a slow consumer must never stall
    Zenoh's receive thread long enough to close the transport. With a `decoder` (both planes'
    subscriptions) raw envelopes are queued and :meth:`get` verifies and decodes them on the
    reader's thread, never on Zenoh's (their timestamps judged at arrival: see
    ``Verifier.open``'s ``received_ns``); without one, :meth:`offer` queues items as they are.
    """

    def __init__(
        self,
        maxsize: int,
        decoder: Callable[[str, bytes], Any] | None,
        accounting: Accounting,
        plane: str,
        block_s: float = 1.0,
        on_full: Callable[[Any, str], None] | None = None,
    ) -> None:
        self._queue: queue.Queue[Any] = queue.Queue(maxsize)
        self._decoder = decoder
        self._on_full = on_full
        self._acct = accounting
        self._plane = plane
        self._block_s = block_s
        self.maxsize = maxsize
        #: the Zenoh subscriber feeding it (control plane), for Fabric.unsubscribe
        self.subscription: Any = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key, raw, peer = _take(sample, self._acct, self._plane)
        self.offer((key, raw, time.time_ns()), peer)

    def offer(self, item: Any, peer: str) -> None:
        """Queue `item` (from `peer`), waiting at most `block_s` for space; else drop it and count
        the drop (through `on_full` when given: it decides whose drop it is)."""
        try:
            self._queue.put(item, timeout=self._block_s)
        except queue.Full:
            if self._on_full is not None:
                self._on_full(item, peer)
            else:
                self._acct.dropped(self._plane, "backpressure", peer)

    def get(self, timeout: float | None = None) -> Any | None:
        """Next valid message, or None after `timeout`. Invalid ones are counted and skipped.

        Up to ``maxsize`` queued messages are still looked at past the deadline, so a forged
        flood cannot hide a valid message from a reader that polls, yet control comes back.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        late = 0
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                item = self._queue.get(timeout=remaining)
            except queue.Empty:
                return None
            if self._decoder is None:
                return item
            msg = self._decoder(*item)
            if msg is not None:
                return msg
            if deadline is not None and time.monotonic() >= deadline:
                late += 1
                if late > self.maxsize:
                    return None

    def get_nowait(self) -> Any | None:
        return self.get(timeout=0.0)

    def depth(self) -> int:
        return self._queue.qsize()


class Fabric:
    """Two Zenoh sessions (data, ctrl), signed control traffic, accounting, liveliness.

    `name` is this process's name in the run (its key suffix); `data_conf` None: no data plane.
    With `identity` every envelope carries this process's certified signature and every envelope
    opened must carry one that passes :func:`authorize`; without, the run secret alone
    authenticates (any holder may claim any name).
    """

    def __init__(
        self,
        *,
        run: str,
        name: str,
        ctrl_conf: zenoh.Config,
        data_conf: zenoh.Config | None,
        secret: bytes,
        open_timeout_s: float = 30.0,
        max_age_s: float = 120.0,
        identity: Identity | None = None,
    ) -> None:
        self.keys = KeySpace(run)
        self.name = name
        self.accounting = Accounting()
        if identity is not None and identity.run != run:
            raise ValueError(f"{name}: identity of run {identity.run!r} used in run {run!r}")
        self.identity = identity
        #: the one actor whose weights this process follows (None: any certified actor)
        self.weights_source: str | None = None
        #: names whose credentials the operator revoked: whatever they sign is `unauthorized`
        self.revoked: set[str] = set()
        self._signer = Signer(secret, name, identity=identity)
        self._verifier = Verifier(secret, max_age_s=max_age_s, run=run,
                                  operator=identity.operator_public if identity is not None else None)
        self._servers: list[_QueryWorker] = []
        self._declared: list[Any] = []
        self._publishers: dict[str, Any] = {}
        self._pub_lock = threading.Lock()
        self._traj_lock = threading.Lock()
        self._traj_buf = bytearray()
        #: the largest envelope each plane sends: the plane's own reassembly cap, which every
        #: session of a run shares; Zenoh would drop a larger one at the receiver, uncounted
        self.send_cap = {CTRL: _message_cap(ctrl_conf), DATA: _message_cap(data_conf) if data_conf is not None else 0}
        self.ctrl = _open_retrying(ctrl_conf, open_timeout_s, "ctrl")
        try:
            self.data = _open_retrying(data_conf, open_timeout_s, "data") if data_conf is not None else None
        except BaseException:
            self.ctrl.close()
            raise
        self._closed = False

    # ------------------------------------------------------------------ data plane
    def publish_traj(self, chunk: Any) -> int:
        """Encode a TrajectoryChunk of this process and send it on the data plane; returns
        bytes sent. The encoding copies the chunk's arrays, so the caller may refill them as
        soon as this returns."""
        if chunk.rollout != self.name:
            raise ValueError(f"{self.name}: chunk of rollout {chunk.rollout!r} (receivers reject it)")
        key = self.keys.traj(self.name)
        with self._traj_lock:  # one reused buffer for the encoding; the envelope is a new one
            n = encode_into(chunk, self._traj_buf)
            envelope = self._signer.seal(key, memoryview(self._traj_buf)[:n])
        if self._oversize(DATA, key, envelope):
            return 0
        self._publisher(DATA, key).put(envelope)
        self.accounting.sent(DATA, len(envelope), self.name)
        return len(envelope)

    def subscribe_traj(self, maxsize: int, expect: type, block_s: float = 1.0, rollout: str = "*",
                       on_dropped: Callable[[Any], None] | None = None) -> Inbox:
        """Bounded inbox of TrajectoryChunks from every (or one) rollout.

        Zenoh's receive thread only copies each envelope out and queues it (waiting up to
        `block_s` for room: backpressure); :meth:`Inbox.get` verifies and decodes (zero-copy) on
        the reader's thread, so authentication never holds a receive thread that the control
        plane's links share. An envelope that fails authentication, or comes from another
        rollout than its key names, is counted under :data:`UNAUTHENTICATED`, never under the
        rollout's name; one that does not decode or names another sender is counted as that
        sender's reject; only verified, decoded chunks are returned. An envelope that finds no
        room within `block_s` is verified there (rare: a consumer stalled that long) and counted
        as its sender's ``dropped.backpressure``, or as an unauthenticated reject; `on_dropped` (on
        Zenoh's thread: it must not block) then gets the dropped chunk when it decodes, so the reader
        knows how far its sender's chunks got even when the last one was dropped.
        """
        if self.data is None:
            raise RuntimeError(f"{self.name}: this fabric was opened without a data plane")

        def _verified(key: str, raw: bytes, received_ns: int) -> tuple[str, memoryview] | None:
            """(sending rollout, payload), counted as received from it; None: counted as refused.
            Freshness is judged at `received_ns` (arrival), not after the wait in the inbox."""
            peer = KeySpace.last(key)
            try:
                opened = self._verifier.open(key, raw, received_ns=received_ns)
                refused = self._refusal(key, opened.sender, opened.kind)
                if refused is not None:
                    raise refused
                if opened.sender != peer:
                    raise SignatureError("unauthorized", f"sender {opened.sender!r} on {peer!r}'s key")
            except SignatureError as err:
                self.accounting.received(DATA, len(raw), UNAUTHENTICATED)
                self.accounting.rejected(DATA, err.reason, UNAUTHENTICATED)
                _warn_limited(f"rejected data message on {_short(key)}: {err}")
                return None
            self.accounting.received(DATA, len(raw), peer)
            return peer, opened.payload

        def _open(key: str, raw: bytes, received_ns: int) -> Any | None:
            got = _verified(key, raw, received_ns)
            if got is None:
                return None
            peer, payload = got
            try:
                msg = decode(payload, expect=expect)
            except CodecError as err:
                self.accounting.rejected(DATA, err.reason, peer)
                _warn_limited(f"rejected data message on {_short(key)} from {peer}: {err}")
                return None
            if getattr(msg, "rollout", peer) != peer:
                self.accounting.rejected(DATA, "sender_mismatch", peer)
                _warn_limited(f"rejected data message on {_short(key)} from {peer}: claims sender {msg.rollout!r}")
                return None
            return msg

        def _full(item: tuple[str, bytes, int], _claimed: str) -> None:
            got = _verified(*item)
            if got is None:
                return
            self.accounting.dropped(DATA, "backpressure", got[0])
            if on_dropped is not None:
                try:
                    msg = decode(got[1], expect=expect)
                except CodecError:
                    return  # counted as dropped already; nothing to say where
                if getattr(msg, "rollout", got[0]) == got[0]:
                    on_dropped(msg)

        inbox = Inbox(maxsize, _open, self.accounting, DATA, block_s, on_full=_full)

        def _hand_off(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            inbox.offer((key, sample.payload.to_bytes(), time.time_ns()), KeySpace.last(key))

        key = self.keys.traj(rollout) if rollout != "*" else self.keys.traj_all()
        self._declared.append(self.data.declare_subscriber(key, _on_receive_thread(_hand_off)))
        return inbox

    def _oversize(self, plane: str, key: str, envelope: bytes) -> bool:
        """True (counted as ``dropped.oversize``, not sent) when `envelope` exceeds the plane's cap."""
        if len(envelope) <= self.send_cap[plane]:
            return False
        self.accounting.dropped(plane, "oversize", KeySpace.last(key))
        _warn_limited(f"not sent on {_short(key)}: envelope of {len(envelope)} bytes > the {plane} plane's "
                      f"max_message_size {self.send_cap[plane]} (receivers would drop it)")
        return True

    # ------------------------------------------------------------------ ctrl plane
    def seal(self, key: str, msg: Any) -> bytes:
        return self._signer.seal(key, encode(msg))

    def _refusal(self, key: str, sender: str, kind: str, query: bool = False) -> SignatureError | None:
        """Why `sender` may not send this: ``revoked`` or ``unauthorized`` (None: it may, or this
        fabric checks no identities)."""
        if self.identity is None:
            return None
        if sender in self.revoked:
            return SignatureError("revoked", f"the credential of {kind} {sender!r} was revoked by the operator")
        why = authorize(self.keys, key, sender, kind, query=query, weights_source=self.weights_source)
        return None if why is None else SignatureError("unauthorized", why)

    def open_signed(self, key: str, raw: bytes, expect: type | tuple[type, ...] | None, *, query: bool = False,
                    bind: bytes = b"", fresh: bool = True, received_ns: int | None = None) -> tuple[str, Any] | None:
        """Verify, authorize and decode a control message; None (and counted) when it fails.
        `query`: it is a query's request; `bind`: the nonce a reply must be bound to;
        `fresh=False`: an old envelope kept as proof (no freshness or replay check);
        `received_ns`: its arrival (wall clock), when it waited in a queue since."""
        try:
            sender, kind, payload, _nonce = self._verifier.open(key, raw, bind=bind, fresh=fresh,
                                                                received_ns=received_ns)
            refused = self._refusal(key, sender, kind, query)
            if refused is not None:
                raise refused
        except SignatureError as err:
            self.accounting.rejected(CTRL, err.reason, UNAUTHENTICATED)
            _warn_limited(f"rejected control message on {_short(key)}: {err}")
            return None
        if query and not payload:
            return sender, None  # a request without arguments (e.g. a status query)
        try:
            msg = decode(payload, expect=expect)
        except CodecError as err:
            self.accounting.rejected(CTRL, err.reason, sender)
            _warn_limited(f"rejected control message on {_short(key)} from {sender}: {err}")
            return None
        return sender, msg

    def publish_ctrl(self, key: str, msg: Any, *, weights: bool = False, sign_key: str | None = None) -> int:
        """Sign and send a control message on `key` (built by `self.keys`); the signature covers
        `sign_key` when given (weights: ``keys.weights_signed()``), else `key`."""
        return self.publish_sealed(key, self.seal(sign_key or key, msg), weights=weights)

    def publish_sealed(self, key: str, envelope: bytes, *, weights: bool = False) -> int:
        """Send an already signed envelope on `key` unchanged (a relay forwarding weights)."""
        if self._oversize(CTRL, key, envelope):
            return 0
        kind = "weights" if weights else "ctrl"
        pub = self._publisher(CTRL, key, kind)
        pub.put(envelope)
        self.accounting.sent(CTRL, len(envelope), KeySpace.last(key))
        return len(envelope)

    def subscribe_ctrl(
        self, key: str, maxsize: int, expect: type | tuple[type, ...] | None, block_s: float = 1.0, *,
        sign_key: str | None = None, with_envelope: bool = False,
    ) -> Inbox:
        """Bounded inbox of verified (sender, message) pairs from `key`, checked against
        `sign_key` when given (else `key`); with `with_envelope`, (sender, message, envelope
        bytes) so the reader can forward the envelope unchanged."""

        def _decode(k: str, raw: bytes, received_ns: int) -> tuple[Any, ...] | None:
            got = self.open_signed(sign_key or k, raw, expect, received_ns=received_ns)
            if got is not None and with_envelope:
                return (*got, raw)
            return got

        inbox = Inbox(maxsize, _decode, self.accounting, CTRL, block_s)
        # Zenoh's default hand-off thread here (unlike the data plane): a full weights inbox
        # holds that thread, and the receive task only once zenoh-python has queued 256 samples.
        inbox.subscription = self.ctrl.declare_subscriber(key, inbox._on_sample)
        self._declared.append(inbox.subscription)
        return inbox

    def unsubscribe(self, inbox: Inbox) -> None:
        """Ends `inbox`'s subscription (call it from a lane, never from a Zenoh callback)."""
        sub, inbox.subscription = inbox.subscription, None
        if sub is None:
            return
        if sub in self._declared:
            self._declared.remove(sub)
        try:
            sub.undeclare()
        except Exception:  # the session is closing: nothing left to stop
            pass

    def on_ctrl(self, key: str, expect: type | tuple[type, ...] | None, handler: Callable[[str, Any], None]) -> None:
        """Call `handler(sender, msg)` for each verified message on `key`, from Zenoh's thread: for
        rare messages (commands) whose handler only sets flags."""

        def _cb(sample: zenoh.Sample) -> None:
            k, raw, _peer = _take(sample, self.accounting, CTRL)
            got = self.open_signed(k, raw, expect)
            if got is not None:
                try:
                    handler(*got)
                except Exception:  # a handler bug must not kill Zenoh's callback thread
                    log.exception("control handler for %s failed", k)

        self._declared.append(self.ctrl.declare_subscriber(key, _cb))

    def serve(self, key: str, handler: Callable[[Any], Any | None], expect: type | None = None, *,
              worker: bool = False, backlog: int = 4) -> None:
        """Queryable on `key`: `handler(request_msg)` returns a message (or its encoded bytes)
        to reply with, a list of them (one reply each), or None for no reply.

        Only signed, authorized requests reach the handler; each reply is bound to its request's
        nonce. With `worker`, verified requests wait in a queue of `backlog` for one thread of
        their own (expensive replies never run on Zenoh's receive thread); a request finding it
        full is dropped and counted (``dropped.query_backlog``).
        """

        def _answer(query: zenoh.Query, req: Any, nonce: bytes) -> None:
            try:
                reply = handler(req)
                if reply is None:
                    return
                for one in reply if isinstance(reply, list) else [reply]:
                    # Handlers may return an already encoded message to skip re-encoding.
                    body = one if isinstance(one, (bytes, bytearray)) else encode(one)
                    payload = self._signer.seal(key, body, bind=nonce)
                    query.reply(key, payload)
                    self.accounting.sent(CTRL, len(payload), "reply")
            except Exception:  # never let a bad request or a handler bug kill the thread
                self.accounting.add(CTRL, "queryable_errors")
                log.exception("queryable %s failed", key)

        pool = _QueryWorker(f"{self.name}-serve-{KeySpace.last(key)}", _answer, backlog, self.accounting) if worker else None
        if pool is not None:
            self._servers.append(pool)

        def _cb(query: zenoh.Query) -> None:
            try:
                raw = query.payload.to_bytes() if query.payload is not None else b""
                self.accounting.received(CTRL, len(raw), "query")
                if not raw:
                    self.accounting.rejected(CTRL, "unsigned", UNAUTHENTICATED)
                    _warn_limited(f"unsigned query on {_short(key)} refused")
                    return
                # The requester signed the key expression it queried, which may be a wildcard
                # matching this queryable (e.g. every status key).
                qkey = str(query.key_expr)
                got = self.open_signed(qkey, raw, expect, query=True)
                if got is None:
                    return
                nonce = nonce_of(raw)
                if pool is None:
                    _answer(query, got[1], nonce)
                else:
                    pool.offer(query, got[1], nonce)
            except Exception:  # never let a bad request kill Zenoh's thread
                self.accounting.add(CTRL, "queryable_errors")
                log.exception("queryable %s failed", key)

        self._declared.append(self.ctrl.declare_queryable(key, _cb))

    def query(
        self, selector: str, request: Any | None = None, *, expect: type | tuple[type, ...] | None = None,
        timeout: float = 2.0, droppable: bool = False,
    ) -> list[tuple[str, Any]]:
        """Query every matching queryable with a signed request (`request`, or an empty payload);
        returns the verified (sender, message) replies bound to this query.

        `droppable` (small repeated queries such as status): a link congested by weights drops the
        query and its replies instead of holding them, under BLOCK, for up to Zenoh's
        ``wait_before_close`` (zconfig.py) with every later status query behind them."""
        payload = self._signer.seal(selector, encode(request) if request is not None else b"")
        nonce = nonce_of(payload)
        # Every reply is kept (no consolidation): a queryable may answer with several (a snapshot
        # in chunks), and each one is verified on its own.
        replies = self.ctrl.get(selector, payload=payload, timeout=timeout, priority=PRIO_CTRL,
                                consolidation=zenoh.ConsolidationMode.NONE,
                                congestion_control=zenoh.CongestionControl.DROP if droppable else zenoh.CongestionControl.BLOCK)
        out = []
        for reply in replies:
            if reply.ok is None:
                continue
            sample = reply.ok
            k = str(sample.key_expr)
            raw = sample.payload.to_bytes()
            self.accounting.received(CTRL, len(raw), KeySpace.last(k))
            got = self.open_signed(k, raw, expect, bind=nonce)
            if got is not None:
                out.append(got)
        return out

    # ------------------------------------------------------------------ membership
    def declare_alive(self) -> None:
        """Hold this process's liveliness token until the fabric closes."""
        self._declared.append(self.ctrl.liveliness().declare_token(self.keys.alive(self.name)))

    def watch_alive(self, handler: Callable[[str, bool], None]) -> None:
        """`handler(role, alive)` on every join/leave, starting with the current members."""

        def _cb(sample: zenoh.Sample) -> None:
            handler(KeySpace.last(str(sample.key_expr)), sample.kind == zenoh.SampleKind.PUT)

        self._declared.append(self.ctrl.liveliness().declare_subscriber(self.keys.alive_all(), _cb, history=True))

    def alive_members(self, timeout: float = 1.0) -> set[str]:
        replies = self.ctrl.liveliness().get(self.keys.alive_all(), timeout=timeout)
        return {KeySpace.last(str(r.ok.key_expr)) for r in replies if r.ok is not None}

    def traj_matched(self) -> bool:
        """Whether a subscriber matches this process's trajectory key (True if unknown)."""
        try:
            return bool(self._publisher(DATA, self.keys.traj(self.name)).matching_status.matching)
        except Exception:  # matching status unavailable: ship as before
            return True

    def on_traj_unmatched(self, callback: Callable[[], None]) -> None:
        """Call `callback` (on a Zenoh thread: it must not block) each time this process's
        trajectory publisher goes from matching a subscriber to matching none: the link to the
        learner broke (a cut, a router restart) or the learner went away. Whatever was still in
        the link's buffers at that moment went down with it (the rollout's ledger records it).
        Nothing to watch without a data session."""
        if self.data is None:
            return
        pub = self._publisher(DATA, self.keys.traj(self.name))

        def _changed(status: Any) -> None:
            if not status.matching:
                callback()
        self._declared.append(pub.declare_matching_listener(_changed))

    # ------------------------------------------------------------------ plumbing
    def _publisher(self, plane: str, key: str, kind: str = "data") -> Any:
        with self._pub_lock:
            pub = self._publishers.get(key)
            if pub is None:
                session = self.data if plane == DATA else self.ctrl
                if session is None:
                    raise RuntimeError(f"{self.name}: no {plane} session")
                prio = {"data": PRIO_DATA, "weights": PRIO_WEIGHTS, "ctrl": PRIO_CTRL}[kind]
                pub = session.declare_publisher(
                    key,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=prio,
                    express=(kind == "ctrl"),
                )
                self._publishers[key] = pub
            return pub

    def close(self) -> None:
        """Undeclare everything and close both sessions (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for pool in self._servers:
            pool.close()
        for entity in [*reversed(self._declared), *self._publishers.values()]:
            try:
                entity.undeclare()
            except Exception:
                pass
        for session in (self.data, self.ctrl):
            if session is not None:
                try:
                    session.close()
                except Exception:
                    pass

    def __enter__(self) -> "Fabric":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _QueryWorker:
    """One named thread answering verified queries from a bounded queue (see Fabric.serve)."""

    def __init__(self, name: str, answer: Callable[[Any, Any, bytes], None], backlog: int,
                 accounting: Accounting) -> None:
        self._answer = answer
        self._acct = accounting
        self._queue: queue.Queue[Any] = queue.Queue(backlog)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def offer(self, query: Any, req: Any, nonce: bytes) -> None:
        try:
            self._queue.put_nowait((query, req, nonce))
        except queue.Full:
            self._acct.dropped(CTRL, "query_backlog", "query")
            _warn_limited("query backlog full: a query was dropped")

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                query, req, nonce = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._answer(query, req, nonce)
            finally:
                del query  # finalizes the query: the requester's get() ends

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                return


_warned: dict[str, float] = {}
_warn_lock = threading.Lock()


def _short(key: str, limit: int = 120) -> str:
    return key if len(key) <= limit else key[:limit] + "..."


def _message_cap(conf: zenoh.Config) -> int:
    return int(json.loads(conf.get_json(MAX_MESSAGE_SIZE_KEY)))


def _warn_limited(text: str, every_s: float = 5.0) -> None:
    """Log a refusal, at most once per `every_s` per kind of message (a flood must not flood
    the log); the counters count every one."""
    kind = text.split(":", 1)[0].split(" on ", 1)[0]
    now = time.monotonic()
    with _warn_lock:
        if now - _warned.get(kind, -every_s) < every_s:
            return
        _warned[kind] = now
    log.warning("%s", text)


def _take(sample: zenoh.Sample, acct: Accounting, plane: str) -> tuple[str, bytes, str]:
    """(key, payload bytes, sending peer) of a received sample, counted as received."""
    key = str(sample.key_expr)
    raw = sample.payload.to_bytes()
    peer = KeySpace.last(key)
    acct.received(plane, len(raw), peer)
    return key, raw, peer


def _on_receive_thread(callback: Callable[[zenoh.Sample], None]) -> Any:
    """`callback` as a handler that runs on Zenoh's receive thread itself.

    zenoh-python's default hand-off thread would let Zenoh keep buffering samples for a stalled
    consumer; run directly, an `Inbox` waiting for space holds the link's receive task and BLOCK
    slows the sender down (hence ``dvla.roles.runtime.size_zenoh_rx``). `indirect` is an
    unstable zenoh-python option: fall back to the default when it is missing.
    """
    try:
        return zenoh.handlers.Callback(callback, indirect=False)
    except TypeError:
        return callback


def _open_retrying(conf: zenoh.Config, timeout_s: float, plane: str) -> zenoh.Session:
    """Open a session; a client whose router is not up yet retries until `timeout_s`.

    Each attempt's handshake is cut to the time left: a listener that accepts but never answers
    (a run that is ending) would otherwise hold one attempt for Zenoh's whole open timeout."""
    deadline = time.monotonic() + timeout_s
    delay = 0.05
    cap_ms = int(json.loads(conf.get_json(OPEN_TIMEOUT_KEY)))
    while True:
        left_ms = int((deadline - time.monotonic()) * 1000)
        conf.insert_json5(OPEN_TIMEOUT_KEY, str(max(100, min(cap_ms, left_ms))))
        try:
            return zenoh.open(conf)
        except zenoh.ZError as err:
            if time.monotonic() >= deadline:
                raise ConnectionError(f"cannot open the {plane} plane session: {err}") from err
            time.sleep(delay)
            delay = min(delay * 2, 0.5)
