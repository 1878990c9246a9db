"""Checks a scan's configuration against this machine before anything is created or deleted.

:func:`sffscan.pipeline.config.config_from_dict` checks the configuration on its own (ranges,
feasibility); :func:`preflight` checks what depends on the machine and the command line:

- torch is installed when the configuration needs it (``processing.backend = "torch"``,
  a focus operator other than GLVM and TENV): it is the extra ``sffscan[torch]``;
- the torch device of ``processing.backend = "torch"`` exists;
- the calibration file ``processing.calibration`` names exists and is a calibration;
- a live ``camera`` source has harvesters and a GenTL producer (``camera.cti``, ...); a
  DAQ set for simulated frames is refused (the simulator drives no lens);
- ``output.path`` can be written: its folder exists and is writable, and an existing path is
  only replaced when ``output.overwrite`` is set and it is an sffscan mosaic (or an empty
  folder);
- a ``--record`` path does not exist yet and its folder is writable;
- the memory the pipeline needs (queues, focus volume, mosaic bands, recorder queue) fits in
  the memory available;
- the simulated world can be built (source.kind ``sim``);
- a transport receiver beyond loopback has its CURVE keys (``sffscan keys``); a tcp
  address can be listened on (a socket is bound to it and closed again: a port another
  program holds is refused here, not after the mosaic was emptied); a loopback receiver's
  pairing folder is this user's alone (mode 0700);
- an output that is a symbolic link is not replaced (the message names the link).

Every failure is a :class:`~sffscan.pipeline.config.ConfigError` naming the field or the path;
``sffscan scan``, ``demo`` and ``replay`` run it first, so ``--overwrite`` deletes nothing
until every check has passed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from sffscan.pipeline.config import ConfigError, ScanConfig

#: share of the available memory a scan may plan to use
MEMORY_SHARE = 0.8


class OutputExists(ConfigError, FileExistsError):
    """``output.path`` exists and may not be replaced: bad input (a :class:`ConfigError`)
    and, as the mosaic writer has always raised it, a :class:`FileExistsError`."""


def available_memory_bytes() -> int | None:
    """``MemAvailable`` of /proc/meminfo (Linux), else physical memory; None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def memory_needed_bytes(cfg: ScanConfig, *, recording: bool = False) -> int:
    """Memory the pipeline of ``cfg`` holds at its peak, bytes (an upper estimate).

    Every queued frame as raw pixels plus two float32 planes (unit-scaled image and focus
    measure), in the ``processing.queue_capacity`` slots of each of the five queues; the
    focus volume's ring (N float32 planes, or the streaming sums); the mosaic's bands
    (four float64 planes of a frame height each); the recorder's queue when recording.
    """
    from sffscan.pipeline.formats.recorder_sink import QUEUE_BYTES, queue_capacity

    o, p, m = cfg.optics, cfg.processing, cfg.motion
    h, w = o.height_px, o.width_px
    px = h * w
    raw = px * np.dtype(o.dtype).itemsize
    per_item = raw + 2 * 4 * px
    queues = 5 * p.queue_capacity * per_item + 2 * per_item
    slack = int(2 * (m.wobble_along_px + m.wobble_across_px)) + 8
    rows = h + 2 * slack
    ring = w + 2 * (p.median_size // 2 + 1) + 2 * p.block_columns + 2 * slack
    planes = 4 + 1 if p.depth_method in ("argmax", "pc", "spc", "centroid") else o.n_levels
    volume = rows * ring * 4 * planes + o.n_levels * max(ring, p.block_columns) * 8 * 4
    bands = (-(-ring // cfg.output.chunk_px) + 2) * rows * cfg.output.chunk_px * 8 * 4
    rec = min(QUEUE_BYTES, queue_capacity(cfg) * raw) if recording else 0
    return int(queues + volume + bands + rec)


#: focus operators the CPU path computes without torch (OpenCV), as
#: :mod:`sffscan.stages.focus_measure` does; the others run in torch
OPENCV_OPERATORS = ("glvm", "tenv")
#: what installs torch for sffscan
TORCH_EXTRA = "pip install 'sffscan[torch]'"


def _installed(module: str) -> bool:
    """``module`` can be imported (found without importing it)."""
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent missing, or sys.modules[module] = None
        return False


def needs_torch(cfg: ScanConfig) -> bool:
    """The scan's focus measure runs in torch: ``processing.backend = "torch"`` or a focus
    operator other than GLVM and TENV."""
    p = cfg.processing
    return p.backend == "torch" or p.focus_operator not in OPENCV_OPERATORS


def check_torch(cfg: ScanConfig) -> None:
    """torch is installed when the configuration needs it (:func:`needs_torch`; torch is the
    optional extra ``sffscan[torch]``)."""
    p = cfg.processing
    if not needs_torch(cfg) or _installed("torch"):
        return
    if p.backend == "torch":
        raise ConfigError(f"processing.backend = 'torch' needs torch, which is not installed: "
                          f"{TORCH_EXTRA} (or use backend = 'opencv')")
    if p.focus_operator not in OPENCV_OPERATORS:
        raise ConfigError(f"processing.focus_operator = {p.focus_operator!r} runs in torch, "
                          f"which is not installed: {TORCH_EXTRA} (or use "
                          f"{' or '.join(OPENCV_OPERATORS)}, which run without it)")


def check_calibration(cfg: ScanConfig) -> None:
    """The file ``processing.calibration`` names can be read, is a calibration and has the
    z response the scan's focus heights come from."""
    path = cfg.processing.calibration
    if not path:
        return
    from sffscan.pipeline.metrology.calibration_model import (
        calibrated_focus_heights,
        load_calibration,
    )

    if not Path(path).is_file():
        raise ConfigError(f"processing.calibration = {path!r}: no such file")
    try:
        calibrated_focus_heights(load_calibration(path), cfg.optics.n_levels)
    except (ConfigError, ValueError) as err:
        raise ConfigError(f"processing.calibration = {path!r}: {err}") from None


def check_hardware(cfg: ScanConfig, *, simulated: bool, camera: bool) -> None:
    """The hardware the configuration names is there, before anything is created: a
    ``camera`` source's GenTL producer and its harvesters package (a missing NI-DAQmx
    driver is found when the camera opens, exit 2). A DAQ configured for a scan whose
    frames are ``simulated`` is refused: the simulator drives no lens (it would be ignored
    without a word)."""
    if cfg.daq.kind == "nidaqmx" and simulated:
        raise ConfigError("daq.kind = 'nidaqmx' with source.kind = 'sim': the simulated "
                          "scanner drives no DAQ, the setting would be ignored; set daq.kind "
                          "= 'sim', or source.kind = 'camera' for the real lens and camera")
    if not camera:
        return
    if not _installed("harvesters"):
        raise ConfigError("source.kind = 'camera' needs harvesters, which is not installed: "
                          "pip install 'sffscan[camera]'")
    from sffscan.pipeline.hardware.camera_source import find_cti

    find_cti(cfg)  # ConfigError naming camera.cti / $SFFSCAN_CTI / $GENICAM_GENTL64_PATH


def _check_device(cfg: ScanConfig) -> None:
    p = cfg.processing
    if p.backend != "torch":
        return
    import torch

    try:
        dev = torch.device(p.device)
    except (RuntimeError, ValueError) as err:
        raise ConfigError(f"processing.device = {p.device!r}: not a torch device ({err})"
                          ) from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"processing.device = {p.device!r}: no CUDA device on this "
                              "machine (use 'cpu')")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"processing.device = {p.device!r}: this machine has "
                              f"{torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps":
        if not torch.backends.mps.is_available():
            raise ConfigError(f"processing.device = {p.device!r}: MPS is not available here")
    elif dev.type != "cpu":
        raise ConfigError(f"processing.device = {p.device!r}: only cpu, cuda and mps "
                          "devices are supported")


def _writable_folder(path: Path, what: str) -> None:
    parent = path.resolve().parent
    if not parent.is_dir():
        raise ConfigError(f"{what} {path}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{what} {path}: the folder {parent} is not writable")


def check_output(cfg: ScanConfig, *, resume: bool = False) -> None:
    """``output.path`` can be written (and replaced only if allowed and a mosaic)."""
    from sffscan.pipeline.mosaic.writer import is_replaceable

    out = Path(cfg.output.path)
    if resume:
        if not out.exists():
            raise ConfigError(f"output.path {out}: no mosaic to resume")
        return
    _writable_folder(out, "output.path")
    if out.is_symlink():
        raise ConfigError(f"output.path {out}: is a symbolic link (to {os.readlink(out)}); "
                          "give the mosaic's real path, a link is never replaced")
    if out.exists():
        if not cfg.output.overwrite:
            raise OutputExists(f"output.path {out}: exists (set output.overwrite, or "
                              "--overwrite, or choose another path)")
        if not is_replaceable(out):
            raise OutputExists(f"output.path {out}: exists and is not an sffscan mosaic nor "
                              "an empty folder; refusing to overwrite it")


def check_record(cfg: ScanConfig, record: str | Path) -> None:
    """A ``--record`` path is new, writable and not the mosaic's."""
    rec = Path(record)
    if rec.exists():
        raise ConfigError(f"--record {rec}: exists; a recording is never overwritten, choose "
                          "another path")
    _writable_folder(rec, "--record")
    if rec.resolve() == Path(cfg.output.path).resolve():
        raise ConfigError(f"--record {rec}: is also output.path")


def check_memory(cfg: ScanConfig, *, recording: bool = False,
                 available: int | None = None) -> None:
    """The pipeline's memory (:func:`memory_needed_bytes`) fits the memory available."""
    need = memory_needed_bytes(cfg, recording=recording)
    have = available if available is not None else available_memory_bytes()
    if have is not None and need > MEMORY_SHARE * have:
        o, p = cfg.optics, cfg.processing
        raise ConfigError(
            f"the scan needs about {need / 2**30:.1f} GiB of memory, more than "
            f"{MEMORY_SHARE:.0%} of the {have / 2**30:.1f} GiB available: frames of "
            f"optics.width_px x optics.height_px = {o.width_px} x {o.height_px} px, "
            f"processing.queue_capacity = {p.queue_capacity}, optics.n_levels = "
            f"{o.n_levels}, processing.block_columns = {p.block_columns}")


def check_world(cfg: ScanConfig) -> None:
    """The simulated world of source.kind ``sim`` can be built."""
    if cfg.source.kind != "sim":
        return
    from sffscan.pipeline.sim_source import make_world

    try:
        make_world(cfg)
    except ValueError as err:
        raise ConfigError(f"source.plate_length_mm / source.plate_width_mm: cannot build the "
                          f"simulated world: {err}") from None


def check_transport(cfg: ScanConfig, address: str | None) -> None:
    """A receiver beyond loopback has its CURVE keys and authorised senders."""
    if address is None and cfg.source.kind != "tcp":
        return
    from sffscan.pipeline.formats.transport import check_address, is_loopback
    from sffscan.pipeline.formats.transport_auth import keys_dir_of, load_pair

    address = check_address(address if address is not None else cfg.source.address)
    check_listen(address)
    if is_loopback(address):
        check_pairing_folder(address)
        return
    folder = keys_dir_of(cfg)
    load_pair(folder, "receiver")
    if not any((folder / "authorized").glob("*.key")):
        raise ConfigError(f"source.keys_dir {folder}: no authorised sender key in "
                          f"{folder / 'authorized'} (make them with 'sffscan keys')")


def _tcp_host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of ``tcp://HOST:PORT`` with a numeric port, else None (ipc, ``*``
    ports and interface names are left to the transport)."""
    if not address.startswith("tcp://"):
        return None
    host, _, port = address[len("tcp://"):].rpartition(":")
    if not port.isdigit() or not host:
        return None
    host = host.strip("[]")
    return ("0.0.0.0" if host == "*" else host), int(port)


def check_listen(address: str) -> None:
    """A ``tcp://HOST:PORT`` address can be listened on: a socket is bound to it (with
    SO_REUSEADDR, as zmq binds) and closed again at once."""
    import socket

    hp = _tcp_host_port(address)
    if hp is None:
        return
    host, port = hp
    infos = None
    for family in (socket.AF_INET, socket.AF_UNSPEC):  # zmq listens on IPv4 by default
        try:
            infos = socket.getaddrinfo(host, port, family, socket.SOCK_STREAM, 0,
                                       socket.AI_PASSIVE)
            break
        except OSError:
            continue
    if not infos:  # an interface name or an unknown host: the transport says
        return
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(addr)
        except OSError as err:
            raise ConfigError(f"{address}: cannot listen: {err.strerror or err} (another "
                              "program holds the port?); nothing was changed") from None


def check_pairing_folder(address: str) -> None:
    """The folder of a loopback receiver's pairing file, if it exists, belongs to this
    user with mode 0700 (it is created so otherwise)."""
    from sffscan.pipeline.formats.transport_auth import pairing_path

    folder = pairing_path(address).parent
    try:
        st = folder.stat()
    except FileNotFoundError:
        return
    except OSError as err:
        raise ConfigError(f"{folder}: cannot use the pairing folder ({err})") from None
    if not folder.is_dir() or (hasattr(os, "getuid") and (st.st_uid != os.getuid()
                                                          or st.st_mode & 0o077)):
        raise ConfigError(f"{folder}: the pairing folder must be a folder of this user with "
                          f"mode 0700 (it is mode {st.st_mode & 0o777:o}; it holds secrets); "
                          "nothing was changed")


def preflight(cfg: ScanConfig, *, record: str | Path | None = None, resume: bool = False,
              simulated: bool | None = None, source: str | None = None,
              live: bool = True) -> None:
    """Every check of this module; raises :class:`ConfigError` at the first failure.

    ``simulated`` says whether the frames come from the simulator (default: when
    ``source.kind`` is ``sim``); a replay or a tcp source builds no world. ``source`` is a
    ``--source`` address; a ``live`` scan (not a replay) from a transport beyond loopback
    has its CURVE keys checked.
    """
    sim = simulated if simulated is not None else cfg.source.kind == "sim"
    check_torch(cfg)
    _check_device(cfg)
    check_calibration(cfg)
    check_hardware(cfg, simulated=live and sim,
                   camera=live and source is None and cfg.source.kind == "camera")
    if live:
        check_transport(cfg, source)
    check_memory(cfg, recording=record is not None)
    if sim:
        check_world(cfg)
    if record is not None:
        check_record(cfg, record)
    check_output(cfg, resume=resume)
