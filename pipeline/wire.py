"""Stage messages between processes: a JSON header, the arrays in shared-memory slots.

:func:`encode` turns a pipeline item (:class:`~sffscan.stages.messages.Frame`,
``PlacedFrame``, ``FocusFrame``, ``DepthBlock``, a sink's ``Tapped`` item, ``None`` or the
end of stream) into JSON bytes: the typed headers as their pydantic JSON, the scalar fields
as JSON values (floats round-trip exactly), and for each array a reference to shared
memory. An array that already lies in a slot of one of the pools (a frame written into the
frame ring by the source) is passed by reference, its slot's count raised; the others are
copied, together, into one free slot of the smallest pool that holds them and takes that
message type (:attr:`~sffscan.pipeline.shm_ring.PoolSpec.kinds`). Pixel data is
never pickled. :func:`decode` rebuilds the item with arrays that are views of the slots;
each view releases its count of the slot when it is garbage (:mod:`sffscan.pipeline.shm_ring`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from sffscan.pipeline.shm_ring import SlotPool, aligned
from sffscan.stages.messages import (
    DepthBlock,
    DepthBlockHeader,
    FocusFrame,
    Frame,
    FrameHeader,
    PlacedFrame,
)
from sffscan.stages.protocol import END_OF_STREAM, Tapped


class WireError(TypeError):
    """An item that cannot travel between processes."""


def _fields(item: Any, arrays: list[np.ndarray]) -> dict[str, Any]:
    """JSON-able description of ``item``; its arrays are appended to ``arrays``."""

    def arr(a: np.ndarray) -> int:
        arrays.append(a)
        return len(arrays) - 1

    if item is None:
        return {"t": "none"}
    if item is END_OF_STREAM:
        return {"t": "eos"}
    if isinstance(item, Frame):
        return {"t": "frame", "h": item.header.model_dump(mode="json"), "image": arr(item.image)}
    if isinstance(item, PlacedFrame):
        return {"t": "placed", "h": item.header.model_dump(mode="json"),
                "image": arr(item.image), "pred": list(item.predicted_px),
                "off": list(item.offset_px), "corr": list(item.correction_px)}
    if isinstance(item, FocusFrame):
        return {"t": "focus", "placed": _fields(item.placed, arrays),
                "image01": arr(item.image01), "focus": arr(item.focus), "col0": item.col0}
    if isinstance(item, DepthBlock):
        return {"t": "block", "h": item.header.model_dump(mode="json"),
                "height": arr(item.height_um), "texture": arr(item.texture),
                "conf": arr(item.confidence),
                "unc": None if item.uncertainty_um is None else arr(item.uncertainty_um)}
    if isinstance(item, Tapped):
        return {"t": "tap", "stage": item.stage, "item": _fields(item.item, arrays)}
    raise WireError(f"{type(item).__name__} cannot be sent between processes")


def _build(d: dict[str, Any], arrays: Sequence[np.ndarray]) -> Any:
    t = d["t"]
    if t == "none":
        return None
    if t == "eos":
        return END_OF_STREAM
    if t == "frame":
        return Frame(FrameHeader.model_validate(d["h"]), arrays[d["image"]])
    if t == "placed":
        return PlacedFrame(FrameHeader.model_validate(d["h"]), arrays[d["image"]],
                           (d["pred"][0], d["pred"][1]), (d["off"][0], d["off"][1]),
                           (d["corr"][0], d["corr"][1]))
    if t == "focus":
        return FocusFrame(_build(d["placed"], arrays), arrays[d["image01"]],
                          arrays[d["focus"]], d["col0"])
    if t == "block":
        unc = d.get("unc")
        return DepthBlock(DepthBlockHeader.model_validate(d["h"]), arrays[d["height"]],
                          arrays[d["texture"]], arrays[d["conf"]],
                          None if unc is None else arrays[unc])
    if t == "tap":
        return Tapped(d["stage"], _build(d["item"], arrays))
    raise WireError(f"unknown message type {t!r}")


def encode(item: Any, pools: Sequence[SlotPool], stop: Callable[[], bool],
           *, extra: dict[str, Any] | None = None) -> bytes:
    """JSON bytes of ``item``; its arrays go by reference into ``pools`` (see module doc).

    The message holds one count of every slot it names: :func:`decode` hands them to the
    receiver's arrays, :func:`discard` gives them back if the message is not delivered.
    """
    arrays: list[np.ndarray] = []
    body = _fields(item, arrays)
    refs: list[dict[str, Any] | None] = [None] * len(arrays)
    copies: list[int] = []
    for i, a in enumerate(arrays):
        for p, pool in enumerate(pools):
            loc = pool.locate(a)
            if loc is not None:
                pool.incref(loc[0])
                refs[i] = {"p": p, "s": loc[0], "o": loc[1], "shape": list(a.shape),
                           "strides": list(a.strides), "dtype": a.dtype.str}
                break
        else:
            copies.append(i)
    if copies:
        need = sum(aligned(arrays[i].nbytes) for i in copies)
        kind = body["item"]["t"] if body["t"] == "tap" else body["t"]
        fits = [p for p, pool in enumerate(pools) if pool.spec.slot_bytes >= need
                and kind in pool.spec.kinds]
        fits = fits or [p for p, pool in enumerate(pools) if pool.spec.slot_bytes >= need
                        and not pool.spec.kinds]
        if not fits:
            for r in refs:
                if r is not None:
                    pools[r["p"]].decref(r["s"])
            raise WireError(f"{type(item).__name__}: {need} bytes of arrays fit no "
                            "shared-memory slot")
        p = min(fits, key=lambda k: pools[k].spec.slot_bytes)
        pool = pools[p]
        slot = pool.acquire(stop)
        for _ in copies[1:]:
            pool.incref(slot)
        view = pool.slot_view(slot)  # our own count, released with ``view``
        pool.incref(slot)
        offset = 0
        for i in copies:
            a = arrays[i]
            dst = np.ndarray(a.shape, a.dtype, buffer=view, offset=offset)
            np.copyto(dst, a, casting="no")
            refs[i] = {"p": p, "s": slot, "o": offset, "shape": list(a.shape),
                       "strides": list(dst.strides), "dtype": a.dtype.str}
            offset += aligned(a.nbytes)
        del dst, view
    msg = {"body": body, "arrays": refs}
    if extra:
        msg["x"] = extra
    return json.dumps(msg, separators=(",", ":")).encode()


def decode(data: bytes, pools: Sequence[SlotPool]) -> tuple[Any, dict[str, Any]]:
    """The item of :func:`encode`'s bytes (arrays are slot views) and its ``extra``."""
    msg = json.loads(data)
    arrays = [pools[r["p"]].array(r["s"], offset=r["o"], shape=tuple(r["shape"]),
                                  dtype=r["dtype"], strides=tuple(r["strides"]))
              for r in msg["arrays"]]
    return _build(msg["body"], arrays), msg.get("x", {})


def discard(data: bytes, pools: Sequence[SlotPool]) -> None:
    """Give back the slot counts of a message that will not be delivered."""
    for r in json.loads(data)["arrays"]:
        pools[r["p"]].decref(r["s"])
