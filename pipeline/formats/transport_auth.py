"""Authentication of the frame transport (:mod:`sffscan.pipeline.formats.transport`).

Loopback: a per-scan secret in a pairing file only this user can read, and a keyed
BLAKE2b-256 tag on every message header. Beyond loopback: CURVE key pairs made by
``sffscan keys`` (zmq's certificates: ``receiver.key``/``.key_secret``,
``sender.key``/``.key_secret``, ``authorized/`` holding the public keys the receiver
accepts). Why a tag of the header only: the header holds the pixels' CRC-32, which the
receiver checks, and a third process on this machine cannot see the traffic on loopback, so
it cannot reuse a tagged header; hashing 2.6 MB frames at 150 frames/s would cost a core.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import tempfile
from pathlib import Path

from sffscan.pipeline.config import ConfigError, ScanConfig

#: bytes of the authentication tag (keyed BLAKE2b)
TAG_BYTES = 32


def _private_dir(base: Path) -> Path:
    """``base`` created with mode 0700, refused if another user owns it or can enter it."""
    base.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = base.stat()
    if hasattr(os, "getuid") and (st.st_uid != os.getuid() or st.st_mode & 0o077):
        raise ConfigError(f"{base}: must belong to this user with mode 0700 (it holds secrets)")
    return base


def pairing_path(address: str) -> Path:
    """The pairing file of a loopback receiver at ``address`` (see the module notes)."""
    root = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    uid = os.getuid() if hasattr(os, "getuid") else 0
    name = hashlib.sha256(address.encode()).hexdigest()[:24]
    return Path(root) / f"sffscan-{uid}" / f"{name}.secret"


def write_pairing(address: str) -> bytes:
    """Draw a new per-scan secret for ``address`` and write its pairing file (mode 0600)."""
    path = pairing_path(address)
    _private_dir(path.parent)
    secret = secrets.token_bytes(32)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, secret.hex().encode())
    finally:
        os.close(fd)
    os.replace(tmp, path)
    return secret


def read_pairing(address: str) -> bytes | None:
    """The secret of the receiver at ``address``, or None while there is none."""
    try:
        text = pairing_path(address).read_text(encoding="ascii").strip()
        return bytes.fromhex(text) if len(text) == 64 else None
    except (OSError, ValueError):
        return None


def remove_pairing(address: str, secret: bytes) -> None:
    """Remove the pairing file if it still holds ``secret`` (not a later receiver's)."""
    if read_pairing(address) == secret:
        try:
            pairing_path(address).unlink()
        except OSError:
            pass


def default_keys_dir() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "sffscan" / "keys"


def keys_dir_of(cfg: ScanConfig | None, keys_dir: str | Path | None = None) -> Path:
    if keys_dir is not None:
        return Path(keys_dir)
    if cfg is not None and cfg.source.keys_dir:
        return Path(cfg.source.keys_dir)
    return default_keys_dir()


def make_keys(folder: str | Path, *, overwrite: bool = False) -> list[Path]:
    """Create the CURVE key pairs ``receiver`` and ``sender`` in ``folder`` (mode 0700) and
    authorise the sender's public key (``authorized/sender.key``); returns the files."""
    import shutil

    import zmq.auth

    d = _private_dir(Path(folder))
    names = ["receiver.key", "receiver.key_secret", "sender.key", "sender.key_secret"]
    if not overwrite and any((d / n).exists() for n in names):
        raise ConfigError(f"{d}: keys exist already (pass --overwrite to replace them)")
    for who in ("receiver", "sender"):
        zmq.auth.create_certificates(str(d), who)
    auth = _private_dir(d / "authorized")
    shutil.copyfile(d / "sender.key", auth / "sender.key")
    for n in names:
        (d / n).chmod(0o600 if n.endswith("_secret") else 0o644)
    return [d / n for n in names] + [auth / "sender.key"]


def load_pair(folder: Path, who: str) -> tuple[bytes, bytes]:
    import zmq.auth

    path = folder / f"{who}.key_secret"
    try:
        public, secret = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: no CURVE key ({err}); make the keys with 'sffscan keys "
                          f"--dir {folder}' (source.keys_dir)") from None
    if secret is None:
        raise ConfigError(f"{path}: holds no secret key")
    return public, secret


def load_public(folder: Path, who: str) -> bytes:
    import zmq.auth

    path = folder / f"{who}.key"
    try:
        return zmq.auth.load_certificate(str(path))[0]
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: no CURVE public key ({err}); copy it from the "
                          "receiver's keys folder") from None


def auth_tag(secret: bytes, header: bytes) -> bytes:
    """The authentication tag of a header: keyed BLAKE2b-256."""
    return hashlib.blake2b(header, key=secret, digest_size=TAG_BYTES).digest()
