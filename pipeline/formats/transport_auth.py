"""Authentication of the frame transport (:mod:`sffscan.pipeline.formats.transport`).

Loopback: a per-scan secret in a pairing file only this user can read, and a keyed
BLAKE2b-256 tag on every message header. Beyond loopback: CURVE key pairs made by
``sffscan keys`` (zmq's certificates: ``receiver.key``/``.key_secret``,
``sender.key``/``.key_secret``, ``authorized/`` holding the public keys the receiver
accepts). Why a tag of the header only: the header holds the pixels' CRC-32, which the
receiver checks, and a third process on this machine cannot see the traffic on loopback, so
it cannot reuse a tagged header; hashing 2.6 MB frames at 150 frames/s would cost a core.

Permissions are checked like ssh does, on every side (``scan --check``, the CURVE receiver,
``grab --keys``, ``grab``'s pairing file), and refused with the path named: a keys folder,
its ``authorized/`` folder or a key file that others can write, a secret key file that
others can read, a pairing folder or file that another user owns or can enter, read or
write. The pairing file is named by the address normalised (:func:`pairing_key`):
``tcp://localhost:P`` and ``tcp://127.0.0.1:P`` are the same receiver.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import stat
import tempfile
from pathlib import Path

from sffscan.pipeline.config import ConfigError, ScanConfig

#: bytes of the authentication tag (keyed BLAKE2b)
TAG_BYTES = 32


def _check_private(path: Path, *, mask: int, what: str) -> None:
    """Refuse ``path`` (ConfigError naming it) if another user owns it or its mode has any
    bit of ``mask`` (group/other permissions). A symbolic link is judged by its target."""
    if not hasattr(os, "getuid"):
        return
    st = path.stat()
    if st.st_uid != os.getuid():
        raise ConfigError(f"{path}: belongs to another user (uid {st.st_uid}); {what} must "
                          "belong to this user")
    if st.st_mode & mask:
        mode = stat.S_IMODE(st.st_mode)
        others = ("readable or writable" if mask & 0o044 else "writable")
        raise ConfigError(f"{path}: mode {mode:04o} is {others} by other users; {what} "
                          f"must not be (chmod {mode & ~mask:04o} {path})")


def _private_dir(base: Path) -> Path:
    """``base`` created with mode 0700, refused if another user owns it or can enter it."""
    base.mkdir(mode=0o700, parents=True, exist_ok=True)
    _check_private(base, mask=0o077, what="a folder of secrets (mode 0700)")
    return base


def pairing_key(address: str) -> str:
    """``address`` normalised for naming its pairing file: ``localhost`` and ``127.0.0.1``
    (and ``::1``, ``[::1]``) are the same host, the port a number, an ipc:// path absolute."""
    if address.startswith("ipc://"):
        return "ipc://" + os.path.abspath(address[len("ipc://"):])
    if not address.startswith("tcp://"):
        return address
    host, sep, port = address[len("tcp://"):].rpartition(":")
    if not sep:
        return address
    host = host.lower()
    if host in ("localhost", "127.0.0.1"):
        host = "127.0.0.1"
    elif host in ("::1", "[::1]"):
        host = "[::1]"
    return f"tcp://{host}:{int(port) if port.isdigit() else port}"


def pairing_path(address: str) -> Path:
    """The pairing file of a loopback receiver at ``address`` (see the module notes)."""
    root = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    uid = os.getuid() if hasattr(os, "getuid") else 0
    name = hashlib.sha256(pairing_key(address).encode()).hexdigest()[:24]
    return Path(root) / f"sffscan-{uid}" / f"{name}.secret"


def check_pairing_dir(address: str) -> None:
    """Refuse (ConfigError naming it) a pairing folder that another user owns or can enter,
    if it exists (a sender before the receiver: nothing to check yet)."""
    folder = pairing_path(address).parent
    if folder.exists():
        _check_private(folder, mask=0o077, what="the pairing folder (mode 0700)")


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
    """The secret of the receiver at ``address``, or None while there is none.

    Raises ConfigError (naming the path) for a pairing folder or file that another user
    owns or can read or write: its secret cannot be trusted."""
    path = pairing_path(address)
    check_pairing_dir(address)
    try:
        _check_private(path, mask=0o077, what="a pairing file (mode 0600)")
    except FileNotFoundError:  # no receiver yet, or it just stopped
        return None
    try:
        text = path.read_text(encoding="ascii").strip()
        return bytes.fromhex(text) if len(text) == 64 else None
    except (OSError, ValueError):
        return None


def remove_pairing(address: str, secret: bytes) -> None:
    """Remove the pairing file if it still holds ``secret`` (not a later receiver's)."""
    try:
        current = read_pairing(address)
    except ConfigError:
        return
    if current == secret:
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


def _check_keys_dir(folder: Path) -> None:
    """A keys folder others can write is refused (they could replace the keys)."""
    if folder.is_dir():
        _check_private(folder, mask=0o022, what="a CURVE keys folder")


def check_authorized_dir(folder: Path) -> None:
    """The receiver's ``authorized/`` folder: present, and neither it nor a key in it
    writable by others (they could authorise themselves)."""
    auth = folder / "authorized"
    if not auth.is_dir():
        raise ConfigError(f"{auth}: no authorised sender keys")
    _check_private(auth, mask=0o022, what="the folder of authorised sender keys")
    for key in sorted(auth.glob("*.key")):
        _check_private(key, mask=0o022, what="an authorised sender key")


def load_pair(folder: Path, who: str) -> tuple[bytes, bytes]:
    """The public and secret CURVE keys of ``who``; the folder and the secret key file are
    checked first (see the module notes)."""
    import zmq.auth

    path = folder / f"{who}.key_secret"
    _check_keys_dir(folder)
    if path.exists():
        _check_private(path, mask=0o077, what="a secret key file (mode 0600)")
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
    _check_keys_dir(folder)
    if path.exists():
        _check_private(path, mask=0o022, what="a public key file")
    try:
        return zmq.auth.load_certificate(str(path))[0]
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: no CURVE public key ({err}); copy it from the "
                          "receiver's keys folder") from None


def auth_tag(secret: bytes, header: bytes) -> bytes:
    """The authentication tag of a header: keyed BLAKE2b-256."""
    return hashlib.blake2b(header, key=secret, digest_size=TAG_BYTES).digest()
