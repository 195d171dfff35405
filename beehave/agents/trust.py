"""Who may speak as whom: Ed25519 signatures on agent messages and directory entries, with
names bound to keys by a fleet authority. See ``docs/agents.md`` ("Trust model").

::

    beehave keys init --dir keys          # keys/fleet.key (keep it offline), keys/fleet.pub
    beehave keys issue atv_1 --dir keys   # keys/atv_1.key, keys/atv_1.cert

    trust = Trust.load("atv_1", mode="signed", keys_dir="keys")
    agent = Agent("atv_1", trust=trust)

A **certificate** (schema ``beehave.cert/1``) is a JSON object that names an agent and its
public key, signed by the fleet key::

    {"schema": "beehave.cert/1", "agent": "atv_1", "public_key": "<base64, 32 bytes>",
     "fleet": "<first 16 hex digits of SHA-256 of the fleet's raw public key>",
     "issued_at": 1767225590, "expires_at": 1798761590,
     "signature": "<base64 Ed25519 signature of the fleet key over the canonical form of
                    this object without 'signature'>"}

A signed message or directory entry carries ``"auth": {"certificate": {…},
"signature": "<base64>"}``: the sender's certificate and its Ed25519 signature over the
canonical form of the object without ``auth``. The **canonical form** is the UTF-8 of
``json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False)`` — RFC 8785
(JCS) for everything beehave sends (strings, integers, floats written in their shortest
round-trip form).

Modes: ``open`` (nothing is checked — today's behaviour, the default) and ``signed``
(refuse what is unsigned, signed with a key the fleet did not certify for the claimed
name, altered, or replayed: an old ``message_id``, or a ``sent_at`` outside ± ``window_s``).
An agent with keys signs what it sends in both modes. Without an explicit :class:`Trust`,
an :class:`~beehave.agents.Agent` reads ``BEEHAVE_AGENT_MODE`` and ``BEEHAVE_AGENT_KEYS``.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import logging
import os
import threading
import time
from collections import deque
from enum import Enum
from pathlib import Path
from typing import Any

from beehave.errors import ConfigError

log = logging.getLogger(__name__)

CERT_SCHEMA = "beehave.cert/1"
MODE_ENV = "BEEHAVE_AGENT_MODE"
KEYS_ENV = "BEEHAVE_AGENT_KEYS"
WINDOW_S = 30.0
"""Default replay window: a message whose ``sent_at`` is further than this from the
receiver's clock is refused (hosts of a fleet need synchronised clocks)."""
FLEET_KEY = "fleet.key"
FLEET_PUB = "fleet.pub"


class Mode(Enum):
    """How an agent treats what it receives."""

    OPEN = "open"
    """Nothing is checked: any participant of the DDS domain can speak as any agent."""
    SIGNED = "signed"
    """Only what the fleet's certified keys signed is taken; the rest is refused."""


def canonical(obj: Any) -> bytes:
    """The bytes that are signed (see the module docstring)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False).encode()


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _unb64(text: Any, what: str) -> bytes:
    if not isinstance(text, str):
        raise ValueError(f"{what} must be a base64 string")
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise ValueError(f"{what} is not valid base64") from None


def _crypto() -> Any:
    try:
        from cryptography.hazmat.primitives.asymmetric import ed25519
    except ImportError as exc:  # the ros extra brings it
        raise ConfigError(f"signed agents need the 'cryptography' package "
                          f"(pip install 'beehave-robotics[ros]'): {exc}") from None
    return ed25519


def raw_public(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    raw: bytes = key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return raw


def fingerprint(public_key: Any) -> str:
    """What certificates name their fleet by: 16 hex digits of SHA-256 of the raw key."""
    return hashlib.sha256(raw_public(public_key)).hexdigest()[:16]


# ---------------------------------------------------------------------- files
def _write_private(path: Path, key: Any) -> None:
    from cryptography.hazmat.primitives import serialization

    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(pem)
    os.chmod(path, 0o600)


def _public_pem(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    pem: bytes = key.public_bytes(serialization.Encoding.PEM,
                                  serialization.PublicFormat.SubjectPublicKeyInfo)
    return pem


def load_private_key(path: str | Path) -> Any:
    """An Ed25519 private key from a PEM (PKCS 8) file; ConfigError names the file."""
    from cryptography.hazmat.primitives import serialization

    ed25519 = _crypto()
    data = _read(path, "private key")
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{path}: not a PEM private key without password ({exc})") from None
    if not isinstance(key, ed25519.Ed25519PrivateKey):
        raise ConfigError(f"{path}: an Ed25519 key is needed, this is {type(key).__name__}")
    return key


def load_public_key(path: str | Path) -> Any:
    """An Ed25519 public key from a PEM (SubjectPublicKeyInfo) file."""
    from cryptography.hazmat.primitives import serialization

    ed25519 = _crypto()
    data = _read(path, "public key")
    try:
        key = serialization.load_pem_public_key(data)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{path}: not a PEM public key ({exc})") from None
    if not isinstance(key, ed25519.Ed25519PublicKey):
        raise ConfigError(f"{path}: an Ed25519 key is needed, this is {type(key).__name__}")
    return key


def load_certificate(path: str | Path) -> dict[str, Any]:
    data = _read(path, "certificate")
    try:
        cert = json.loads(data)
    except ValueError as exc:
        raise ConfigError(f"{path}: a certificate is JSON ({exc})") from None
    if not isinstance(cert, dict):
        raise ConfigError(f"{path}: a certificate is a JSON object")
    return cert


def _read(path: str | Path, what: str) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read the {what} {path}: {exc.strerror or exc} (make it "
                          f"with `beehave keys init` / `beehave keys issue NAME`)") from None


def init_fleet(keys_dir: str | Path, *, force: bool = False) -> tuple[Path, Path]:
    """Create the fleet authority: ``fleet.key`` (mode 0600: keep it off the robots) and
    ``fleet.pub`` (every agent of a signed fleet needs it). Refuses to overwrite an existing
    ``fleet.key`` unless ``force``: every certificate it issued would become worthless."""
    ed25519 = _crypto()
    folder = Path(keys_dir)
    folder.mkdir(parents=True, exist_ok=True)
    private, public = folder / FLEET_KEY, folder / FLEET_PUB
    if private.exists() and not force:
        raise ConfigError(f"{private} exists: a new fleet key would void every certificate "
                          f"it issued (use --force to replace it)")
    key = ed25519.Ed25519PrivateKey.generate()
    _write_private(private, key)
    public.write_bytes(_public_pem(key.public_key()))
    return private, public


def issue(keys_dir: str | Path, name: str, *, days: float = 365.0) -> tuple[Path, Path]:
    """A new key for agent ``name`` and its certificate signed by the fleet key in
    ``keys_dir``: ``NAME.key`` (0600) and ``NAME.cert``."""
    from beehave.agents.message import is_agent_name

    ed25519 = _crypto()
    if not is_agent_name(name):
        raise ConfigError(f"agent name {name!r} is not valid: letters, digits and '_', "
                          f"starting with a letter, at most 63 characters")
    if not (days > 0 and days < 36500):
        raise ConfigError(f"days must be > 0 and < 36500, got {days!r}")
    folder = Path(keys_dir)
    fleet = load_private_key(folder / FLEET_KEY)
    key = ed25519.Ed25519PrivateKey.generate()
    now = int(time.time())
    cert: dict[str, Any] = {
        "schema": CERT_SCHEMA, "agent": name, "public_key": _b64(raw_public(key.public_key())),
        "fleet": fingerprint(fleet.public_key()), "issued_at": now,
        "expires_at": now + int(days * 86400)}
    cert["signature"] = _b64(fleet.sign(canonical(cert)))
    key_path, cert_path = folder / f"{name}.key", folder / f"{name}.cert"
    _write_private(key_path, key)
    cert_path.write_text(json.dumps(cert, indent=1) + "\n")
    return key_path, cert_path


def signed_environment(keys_dir: str | Path, names: list[str]) -> dict[str, str]:
    """A new fleet authority in ``keys_dir`` with a certificate for each of ``names``, and
    the environment that puts every agent process started with it in signed mode: what
    ``beehave fleet --signed`` does for the processes it launches."""
    init_fleet(keys_dir, force=True)
    for name in names:
        issue(keys_dir, name)
    return {MODE_ENV: Mode.SIGNED.value, KEYS_ENV: str(Path(keys_dir).resolve())}


# ---------------------------------------------------------------------- trust
class Refused(Exception):
    """Why a signed-mode receiver refused something (the text is the reason)."""


class Trust:
    """One agent's keys and mode. ``Trust()`` is open mode without keys (sends unsigned,
    takes everything)."""

    def __init__(self, mode: Mode | str = Mode.OPEN, *, fleet_public_key: Any = None,
                 key: Any = None, certificate: dict[str, Any] | None = None,
                 window_s: float = WINDOW_S, name: str | None = None) -> None:
        try:
            self.mode = Mode(mode)
        except ValueError:
            raise ConfigError(f"agent {name!r}: mode {mode!r} is not one of "
                              f"{[m.value for m in Mode]}") from None
        if not (isinstance(window_s, int | float) and 0 < window_s <= 86400):
            raise ConfigError(f"agent {name!r}: window_s must be > 0 and at most a day, "
                              f"got {window_s!r}")
        self.window_s = float(window_s)
        self.fleet_public_key = fleet_public_key
        self.key = key
        self.certificate = certificate
        self.fleet = fingerprint(fleet_public_key) if fleet_public_key is not None else None
        if (key is None) != (certificate is None):
            raise ConfigError(f"agent {name!r}: a key needs its certificate and a "
                              f"certificate its key")
        if self.mode is Mode.SIGNED:
            if fleet_public_key is None:
                raise ConfigError(f"agent {name!r}: signed mode needs the fleet's public "
                                  f"key ({FLEET_PUB}, from `beehave keys init`)")
            if key is None:
                raise ConfigError(f"agent {name!r}: signed mode needs the agent's key and "
                                  f"certificate (`beehave keys issue {name or 'NAME'}`)")
        self._lock = threading.Lock()
        self._certs: dict[str, str] = {}  # certificate signature -> its agent (verified)
        self._seen: dict[tuple[str, str], float] = {}  # (sender, message_id) -> sent_at
        self._order: deque[tuple[float, tuple[str, str]]] = deque()
        self._floor = 0.0  # sent_at of the newest id forgotten: older ones are refused
        self._entries: dict[str, float] = {}  # directory: agent -> newest sent_at taken
        if certificate is not None:
            self._check_own(name)

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, name: str, *, mode: Mode | str = Mode.SIGNED,
             keys_dir: str | Path | None = None, fleet_public_key: str | Path | None = None,
             key: str | Path | None = None, certificate: str | Path | None = None,
             window_s: float = WINDOW_S) -> Trust:
        """Keys from files: ``keys_dir`` holds ``fleet.pub``, ``NAME.key`` and
        ``NAME.cert`` (as `beehave keys` writes them); each path given explicitly wins."""
        folder = Path(keys_dir) if keys_dir is not None else None
        pub = fleet_public_key or (folder / FLEET_PUB if folder is not None else None)
        own = key or (folder / f"{name}.key" if folder is not None else None)
        cert = certificate or (folder / f"{name}.cert" if folder is not None else None)
        return cls(mode, name=name, window_s=window_s,
                   fleet_public_key=load_public_key(pub) if pub is not None else None,
                   key=load_private_key(own) if own is not None else None,
                   certificate=load_certificate(cert) if cert is not None else None)

    @classmethod
    def from_env(cls, name: str) -> Trust:
        """``BEEHAVE_AGENT_MODE`` (open, signed) and ``BEEHAVE_AGENT_KEYS`` (a folder from
        `beehave keys`); open without keys when neither is set."""
        mode = os.environ.get(MODE_ENV, "").strip() or Mode.OPEN.value
        keys = os.environ.get(KEYS_ENV, "").strip() or None
        if mode not in {m.value for m in Mode}:
            raise ConfigError(f"{MODE_ENV}={mode!r} is not one of {[m.value for m in Mode]}")
        if keys is None:
            return cls(mode, name=name)
        return cls.load(name, mode=mode, keys_dir=keys)

    def _check_own(self, name: str | None) -> None:
        assert self.certificate is not None and self.key is not None
        cert = self.certificate
        if name is not None and cert.get("agent") != name:
            raise ConfigError(f"agent {name!r}: the certificate is for {cert.get('agent')!r}")
        if self.fleet_public_key is not None:
            try:
                self._verify_cert(cert)
            except Refused as exc:
                raise ConfigError(f"agent {name!r}: own certificate: {exc}") from None
        if cert.get("public_key") != _b64(raw_public(self.key.public_key())):
            raise ConfigError(f"agent {name!r}: the key does not belong to the certificate "
                              f"(its public key differs)")

    @property
    def signing(self) -> bool:
        return self.key is not None

    @property
    def verifying(self) -> bool:
        return self.mode is Mode.SIGNED

    # ------------------------------------------------------------------ signing
    def sign(self, data: dict[str, Any]) -> dict[str, Any]:
        """``data`` with its ``auth`` (``data`` must not hold one)."""
        assert self.key is not None
        signature = self.key.sign(canonical(data))
        return {**data, "auth": {"certificate": self.certificate, "signature": _b64(signature)}}

    def dumps(self, data: dict[str, Any]) -> str:
        """The wire text of ``data``, signed when this agent has keys."""
        if self.key is not None:
            data = self.sign(data)
        return json.dumps(data, separators=(",", ":"), ensure_ascii=False, allow_nan=False)

    # ------------------------------------------------------------------ checking
    def _verify_cert(self, cert: Any) -> str:
        """The agent ``cert`` binds, after checking the fleet's signature and its dates."""
        if not isinstance(cert, dict):
            raise Refused("auth.certificate must be an object")
        signature = cert.get("signature")
        with self._lock:
            known = self._certs.get(signature) if isinstance(signature, str) else None
        if known is None:
            if cert.get("schema") != CERT_SCHEMA:
                raise Refused(f"certificate schema {cert.get('schema')!r} is not "
                              f"{CERT_SCHEMA!r}")
            if cert.get("fleet") != self.fleet:
                raise Refused(f"certificate issued by fleet {cert.get('fleet')!r}, not by "
                              f"this fleet's authority ({self.fleet})")
            body = {k: v for k, v in cert.items() if k != "signature"}
            try:
                self.fleet_public_key.verify(_unb64(signature, "certificate signature"),
                                             canonical(body))
            except Exception as exc:  # InvalidSignature, ValueError
                raise Refused(f"certificate not signed by this fleet's authority "
                              f"({self.fleet}): {type(exc).__name__}") from None
            agent = cert.get("agent")
            if not isinstance(agent, str) or not isinstance(signature, str):
                raise Refused("certificate names no agent")
            with self._lock:
                if len(self._certs) > 10000:
                    self._certs.clear()
                self._certs[signature] = known = agent
        expires = cert.get("expires_at")
        if isinstance(expires, int | float) and expires < time.time():
            raise Refused(f"certificate of {known!r} expired at "
                          f"{time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime(expires))} UTC")
        return known

    def _verify(self, data: dict[str, Any], claimed: str, what: str) -> dict[str, Any]:
        auth = data.get("auth")
        if auth is None:
            raise Refused(f"unsigned {what} from {claimed!r}: this agent runs in signed mode "
                          f"and takes only what a key certified by the fleet signed")
        if not isinstance(auth, dict) or set(auth) != {"certificate", "signature"}:
            raise Refused(f"malformed auth from {claimed!r}: expected an object with "
                          f"'certificate' and 'signature'")
        owner = self._verify_cert(auth["certificate"])
        if owner != claimed:
            raise Refused(f"{what} claims to be from {claimed!r} but is signed with the key "
                          f"certified for {owner!r}")
        ed25519 = _crypto()
        try:
            public = ed25519.Ed25519PublicKey.from_public_bytes(
                _unb64(auth["certificate"].get("public_key"), "certificate public_key"))
            body = {k: v for k, v in data.items() if k != "auth"}
            public.verify(_unb64(auth["signature"], "auth.signature"), canonical(body))
        except Exception as exc:
            raise Refused(f"bad signature on the {what} from {claimed!r} (not signed with "
                          f"the key certified for it, or altered): {type(exc).__name__}") \
                from None
        sent_at = data.get("sent_at")
        if not isinstance(sent_at, int | float) or isinstance(sent_at, bool):
            raise Refused(f"{what} from {claimed!r} has no sent_at")
        skew = sent_at - time.time()
        if abs(skew) > self.window_s:
            raise Refused(f"stale {what} from {claimed!r}: sent_at is {skew:+.1f} s from this "
                          f"host's clock (window ± {self.window_s:g} s; replayed, or clocks "
                          f"not synchronised)")
        return data

    def check_message(self, data: dict[str, Any]) -> None:
        """Raises :class:`Refused` unless ``data`` (a parsed message) is signed by its
        sender's certified key, fresh, and not seen before; remembers its id."""
        sender = data.get("sender")
        self._verify(data, sender if isinstance(sender, str) else "?", "message")
        key = (str(sender), str(data.get("message_id")))
        sent_at = float(data["sent_at"])
        now = time.time()
        with self._lock:
            while self._order and self._order[0][0] < now - 2 * self.window_s:
                _, old = self._order.popleft()
                self._seen.pop(old, None)
            if key in self._seen:
                raise Refused(f"replayed message: message_id {key[1]!r} from {key[0]!r} was "
                              f"taken already")
            if sent_at <= self._floor:
                raise Refused(f"replayed message: {key[1]!r} from {key[0]!r} is older than "
                              f"the messages this agent can still tell apart")
            self._seen[key] = sent_at
            self._order.append((now, key))
            if len(self._order) > 200_000:  # bounded: forget the oldest, refuse older
                _, old = self._order.popleft()
                self._floor = max(self._floor, self._seen.pop(old, 0.0))

    def check_entry(self, data: dict[str, Any]) -> None:
        """Raises :class:`Refused` unless the directory entry ``data`` is signed by the key
        certified for its ``agent``, fresh, and not older than one taken before."""
        agent = data.get("agent")
        claimed = agent if isinstance(agent, str) else "?"
        self._verify(data, claimed, "directory entry")
        sent_at = float(data["sent_at"])
        with self._lock:
            if sent_at < self._entries.get(claimed, 0.0):
                raise Refused(f"replayed directory entry of {claimed!r}: older than one "
                              f"taken before")
            if len(self._entries) > 10000:
                self._entries.clear()
            self._entries[claimed] = sent_at

    def __repr__(self) -> str:
        who = self.certificate.get("agent") if self.certificate else None
        return f"<Trust {self.mode.value} key={who!r} fleet={self.fleet}>"
