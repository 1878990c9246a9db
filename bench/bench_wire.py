"""What one message between the scan's processes costs (issue 28, "transport"): CPU per
message of the JSON header (:mod:`sffscan.pipeline.wire`, encode and decode with the real
shared-memory pools) and of one hop through the bounded ``multiprocessing.Queue`` of a
channel (:mod:`sffscan.pipeline.channels`), each side's CPU measured in its own process.

    python bench/bench_wire.py [--messages 3000] [--rounds 3]

The messages are the ones a scan sends: a raw frame and a placed frame whose image lies in
a slot of the frame ring (passed by reference), and a depth block whose four arrays
(1040 x 64 float32) are copied into a slot. Writes bench/results/wire.md. Not a test:
nothing here asserts.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import platform
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from sffscan.pipeline.shm_ring import SlotPool, new_spec
from sffscan.pipeline.wire import decode, encode
from sffscan.stages.messages import DepthBlock, DepthBlockHeader, Frame, FrameHeader, PlacedFrame

OUT = Path(__file__).resolve().parent / "results" / "wire.md"
H, W = 1024, 1280


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _items(frame_ring: SlotPool) -> dict[str, Any]:
    slot = frame_ring.acquire(lambda: False)
    image = np.ndarray((H, W), np.uint16, buffer=frame_ring.slot_view(slot))
    header = FrameHeader(frame_id=7, timestamp_ns=123_456_789, focus_index=3,
                         stage_x_um=1500.25, stage_y_um=-20.5)
    rows = H + 16
    block = DepthBlock(DepthBlockHeader(x0_px=4096, y0_px=-8, width_px=64, height_px=rows,
                                        pass_index=0, complete_columns=64,
                                        incomplete_columns=0),
                       *(np.ones((rows, 64), np.float32) for _ in range(4)))
    return {"frame (by reference)": Frame(header, image),
            "placed frame (by reference)": PlacedFrame(header, image, (3, -1), (2, 0),
                                                       (0.25, -0.5)),
            "depth block (4 arrays copied)": block}


def codec_us(item: Any, pools: list[SlotPool], n: int) -> tuple[float, float, int]:
    """CPU µs per message of encode and of decode (the decoded item dropped at once, which
    gives its slot counts back), and the header's size in bytes."""
    for _ in range(min(n, 20)):  # warm
        decode(encode(item, pools, lambda: False), pools)
    enc = dec = 0.0
    data = b""
    for _ in range(n):
        t = _cpu()
        data = encode(item, pools, lambda: False)
        t1 = _cpu()
        decode(data, pools)
        enc += t1 - t
        dec += _cpu() - t1
    return 1e6 * enc / n, 1e6 * dec / n, len(data)


def _receiver(q: Any, n: int, out: Any) -> None:
    got = 0
    c0 = _cpu()
    while got < n:
        q.get(timeout=30)
        got += 1
    out.put(_cpu() - c0)


def hop_us(size: int, n: int) -> tuple[float, float]:
    """CPU µs per message of put (sender's process, its feeder thread included) and get
    (receiver's process) through a bounded spawn-context queue, as a channel does."""
    ctx = mp.get_context("spawn")
    q, out = ctx.Queue(maxsize=8), ctx.Queue()
    p = ctx.Process(target=_receiver, args=(q, n, out))
    p.start()
    payload = b"x" * size
    c0 = _cpu()  # while the receiver starts, the puts block on the full queue (no CPU)
    for _ in range(n):
        q.put(payload, timeout=60)
    recv = out.get(timeout=120)
    send = _cpu() - c0
    p.join(timeout=30)
    return 1e6 * send / n, 1e6 * recv / n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--messages", type=int, default=3000)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    ctx = mp.get_context("spawn")
    specs = [new_spec("bench-frames", slots=4, slot_bytes=H * W * 2),
             new_spec("bench-blocks", slots=4, slot_bytes=4 * (H + 16) * 64 * 4 + 4096)]
    pools = [SlotPool(s, (ctx.Lock(), ctx.Semaphore(s.slots)), create=True) for s in specs]
    rows: list[str] = []
    try:
        items = _items(pools[0])
        sizes = {}
        for name, item in items.items():
            runs = [codec_us(item, pools, args.messages if "block" not in name
                             else args.messages // 10) for _ in range(args.rounds)]
            enc = statistics.median(r[0] for r in runs)
            dec = statistics.median(r[1] for r in runs)
            sizes[name] = runs[0][2]
            rows.append(f"| {name} | {runs[0][2]} | {enc:.1f} | {dec:.1f} | "
                        + ", ".join(f"{r[0]:.1f}/{r[1]:.1f}" for r in runs) + " |")
            print(rows[-1], flush=True)
        del items
        hops = [hop_us(max(sizes.values()), args.messages) for _ in range(args.rounds)]
    finally:
        for p in pools:
            p.close()
            p.unlink()
    put = statistics.median(h[0] for h in hops)
    get = statistics.median(h[1] for h in hops)
    hop_line = (f"One hop of a {max(sizes.values())}-byte message through a bounded spawn "
                f"queue: put {put:.1f} µs of the sender's CPU (its feeder thread included), "
                f"get {get:.1f} µs of the receiver's (median of {args.rounds} runs of "
                f"{args.messages} messages: " + ", ".join(f"{a:.1f}/{b:.1f}" for a, b in hops)
                + ").")
    print(hop_line)
    text = "\n".join([
        "# Messages between the scan's processes: CPU per message (bench/bench_wire.py)", "",
        f"`python bench/bench_wire.py --messages {args.messages} --rounds {args.rounds}` "
        f"({platform.machine()}, {mp.cpu_count()} cores, Python {sys.version.split()[0]}, "
        f"{time.strftime('%Y-%m-%d %H:%M')}; {time.perf_counter() - t0:.0f} s). CPU time "
        "of this process (getrusage), per message; median of the rounds.", "",
        "| message | JSON header, bytes | encode µs | decode µs | rounds (encode/decode) |",
        "|---|---:|---:|---:|---|", *rows, "", hop_line, ""])
    OUT.write_text(text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
