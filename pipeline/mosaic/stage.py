"""The mosaic stage: depth blocks gathered into chunk-wide bands
(:class:`sffscan.stages.mosaic.BandGatherer`) and each finished band blended into the mosaic
by its writer (:class:`sffscan.pipeline.mosaic.writer.MosaicWriter`)."""

from __future__ import annotations

from collections.abc import Iterator

from sffscan.pipeline.mosaic.writer import MosaicWriter
from sffscan.stages.messages import DepthBlock
from sffscan.stages.mosaic import BandGatherer
from sffscan.stages.protocol import Stage


class MosaicStage(Stage):
    """Gathers depth blocks into chunk-wide bands and writes them into the mosaic."""

    name = "mosaic"
    unit = "blocks"

    def __init__(self, writer: MosaicWriter) -> None:
        self.writer = writer
        self.bands = BandGatherer(chunk_px=writer.chunk, origin_x_px=writer.origin[0])
        self.pass_index: int | None = None
        self.blocks = 0

    def _flush_band(self, cx: int) -> None:
        band = self.bands.take(cx)
        if band is not None:
            self.writer.write_region(band.x0, band.y0, band.sums())

    def process(self, item: DepthBlock) -> Iterator[None]:
        h = item.header
        if self.pass_index is not None and h.pass_index != self.pass_index:
            self.flush()
        self.pass_index = h.pass_index
        self.blocks += 1
        # bands the motion has left behind are final for this pass
        for cx in self.bands.add(item):
            self._flush_band(cx)
        return iter(())

    def flush(self) -> None:
        for cx in self.bands.open_bands():
            self._flush_band(cx)

    def finish(self) -> Iterator[None]:
        self.flush()
        return iter(())

    def close(self, *, failed: bool) -> None:
        # On failure, what is already complete is still written: the mosaic stays readable.
        # Each band is tried on its own, and the status is set whatever happens.
        error: Exception | None = None
        for cx in self.bands.open_bands():
            try:
                self._flush_band(cx)
            except Exception as exc:  # noqa: BLE001 - re-raised below, after the status
                error = error or exc
        failed = failed or error is not None
        self.writer.set_status("failed" if failed else "complete",
                               valid_pixels=self.writer.valid_px, blocks=self.blocks)
        if error is not None:
            raise error

    def extra_stats(self) -> dict[str, int]:
        return {"valid_pixels": self.writer.valid_px,
                "chunks_written": self.writer.blocks_written}
