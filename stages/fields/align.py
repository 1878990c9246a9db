"""Stack alignment: each frame's scale and shift against the middle frame, and the warp.

A non-telecentric lens magnifies differently at each focus position ("focus breathing");
a focus stack taken through it must be aligned before a focus measure compares the frames
pixel by pixel, as the focus-stack program does. Here:

1. each frame is registered to its neighbour toward the middle frame with OpenCV's ECC
   (:func:`cv2.findTransformECC`, affine model, coarse to fine on an image pyramid, each
   pair started from the previous pair's result), on the frames' local contrast
   (:func:`~sffscan.stages.fields.align_pairs.registration_frame`: a tilted part's band of
   focus, moving across the frame, does not pull it), and the pair transforms are chained to
   the middle frame: neighbours differ little in blur, so the correlation holds even where
   the middle frame is sharp and the far frames are not; for ``"scale"``, a step between
   two featureless frames that strays from the others gives way to them (:func:`_smooth_steps`);
2. the chained affine transform is reduced to the model asked for: ``"scale"`` (one
   magnification about the frame centre plus a shift, the breathing of a lens),
   ``"similarity"`` (plus a rotation) or ``"affine"``;
3. each frame is warped onto the middle frame's grid (:func:`align_stack`): a scale and
   shift by a windowed sinc whose flat passband keeps every frame's finest texture
   (:mod:`sffscan.stages.fields.resample`: why), a rotation or shear by OpenCV's Lanczos;
   pixels that any frame does not cover are reported (``valid``), never filled.

:func:`misalignment` is the cheap check a stack gets when alignment is off: the first and
last frames against the middle one.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from sffscan.stages.fields.align_pairs import (
    Model,
    coverage,
    homogeneous,
    invert_step,
    pair_transform,
    reduce_to_model,
    registration_frame,
    scale_step,
    to_float,
)
from sffscan.stages.fields.resample import TAPS, is_separable, warp_frame

__all__ = [
    "Alignment",
    "align_stack",
    "check_alignment",
    "describe_alignment",
    "estimate_alignment",
    "mask_uncovered",
    "misalignment",
    "prepare_stack",
    "warp_frame",
]

log = logging.getLogger(__name__)

#: a drift of the frames' centres over the stack this large (px) gets a note in
#: :func:`describe_alignment`: a pixel of misregistration is where a focus window of a few
#: pixels starts to compare different texture across frames
DRIFT_NOTE_PX = 1.0


@dataclass(frozen=True)
class Alignment:
    """Per-frame transforms onto the reference frame's grid.

    Attributes
    ----------
    matrices : (N, 2, 3) float64
        ``frame_k(A_k [x, y, 1]) ~ reference(x, y)``: reference px -> frame k px.
    scale : (N,) float64
        Magnification of each frame relative to the reference (1.015 = 1.5 % larger).
    shift_px : (N, 2) float64
        Where the reference's centre lands in frame k, minus the centre, px (x, y).
    rotation_deg : (N,) float64
        Rotation of frame k relative to the reference, degrees (0 for ``"scale"``).
    reference : int
        Index of the reference (middle) frame.
    correlation : (N,) float64
        ECC correlation of each frame with its neighbour toward the reference after
        alignment (1 for the reference, NaN where ECC failed and the step was the mean).
    model : str
        ``"scale"``, ``"similarity"`` or ``"affine"``.
    """

    matrices: np.ndarray
    scale: np.ndarray
    shift_px: np.ndarray
    rotation_deg: np.ndarray
    reference: int
    correlation: np.ndarray
    model: str

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (stored in the mosaic's attributes)."""
        return {"model": self.model, "reference": self.reference,
                "scale": [round(float(v), 7) for v in self.scale],
                "shift_px": [[round(float(a), 3), round(float(b), 3)] for a, b in self.shift_px],
                "rotation_deg": [round(float(v), 4) for v in self.rotation_deg],
                "correlation": [round(float(v), 5) for v in self.correlation]}

    @classmethod
    def breathing(cls, scale: np.ndarray, shape: tuple[int, int]) -> Alignment:
        """Known magnifications about the frame centre (a lens' breathing, no shift), e.g.
        from a calibration or a simulator's truth; ``scale``: (N,), ``shape``: (H, W)."""
        s = np.asarray(scale, dtype=np.float64).reshape(-1)
        n = s.size
        c = np.array([(shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0])
        mats = np.array([np.hstack([np.eye(2) * m, (c - m * c)[:, None]]) for m in s])
        return cls(matrices=mats, scale=s.copy(), shift_px=np.zeros((n, 2)),
                   rotation_deg=np.zeros(n), reference=n // 2, correlation=np.ones(n),
                   model="scale")


def estimate_alignment(stack: np.ndarray, *, model: Model = "scale",
                       reference: int | None = None, normalise: bool = True) -> Alignment:
    """Each frame's transform onto the reference (middle) frame, chained through neighbours.

    Parameters
    ----------
    stack : (N, H, W) array of uint8, uint16 or float
        The focus stack, in focus order.
    model : {"scale", "similarity", "affine"}, keyword-only
        Motion model reported and used by :func:`align_stack`.
    reference : int, optional
        Reference frame; default the middle one, ``N // 2``.
    normalise : bool, keyword-only
        Register the frames' local contrast (:func:`~sffscan.stages.fields.align_pairs.
        registration_frame`: a tilted part's moving band of focus does not pull the
        estimate) rather than the frames as taken. Default True.

    Returns an :class:`Alignment`.
    Raises ValueError if the stack is not (N, H, W) or a frame cannot be aligned (named;
    for ``"scale"`` and N >= 6 its step takes the others' mean instead, with a warning).
    """
    st = np.asarray(stack)
    if st.ndim != 3 or st.shape[0] < 1:
        raise ValueError(f"stack must be (N, H, W), got shape {st.shape}")
    if model not in ("scale", "similarity", "affine"):
        raise ValueError(f"model must be 'scale', 'similarity' or 'affine', got {model!r}")
    n = st.shape[0]
    ref = n // 2 if reference is None else int(reference)
    if not 0 <= ref < n:
        raise ValueError(f"reference must be in 0..{n - 1}, got {reference}")
    if normalise:
        st = np.stack([registration_frame(f) for f in st])
    full = [np.eye(3) for _ in range(n)]
    rho = np.ones(n)
    # "scale": the steps frame k - 1 -> k px (log s, shift x, y), their variances (row k)
    steps, variances = np.zeros((n, 3)), np.full((n, 3), np.inf)
    for direction in (-1, 1):
        step_init: np.ndarray | None = None
        k = ref + direction
        while 0 <= k < n:
            j = k - direction
            try:
                a, rho[k] = pair_transform(st[j], st[k], init=step_init)
            except ValueError as err:
                if model != "scale" or n < 6:
                    raise ValueError(f"frame {k}: cannot align to frame {j}: {err}") from None
                # a lens breathes smoothly: the step takes the others' mean (_smooth_steps)
                log.warning(f"frame {k}: ECC did not converge against frame {j} ({err}); "
                            "its scale step is the other steps' mean")
                a, rho[k] = (np.eye(2, 3) if step_init is None else step_init), math.nan
            step_init = a
            full[k] = homogeneous(a) @ full[j]  # reference px -> frame j px -> frame k px
            if model == "scale":
                i = max(j, k)  # the step from frame i - 1 to frame i
                step, var = scale_step(st[j], st[k], a)
                var = np.full(3, np.inf) if math.isnan(rho[k]) else var
                steps[i], variances[i] = (step if direction > 0 else invert_step(step)), var
            k += direction
    if model == "scale" and n >= 6:
        full = _chain_steps(_smooth_steps(steps[1:], variances[1:]), ref, st.shape[1:])
    mats, scales, shifts, rots = zip(*(reduce_to_model(f[:2], st.shape[1:], model) for f in full),
                                     strict=True)
    return Alignment(matrices=np.array(mats), scale=np.array(scales), shift_px=np.array(shifts),
                     rotation_deg=np.array(rots), reference=ref, correlation=rho, model=model)


def _smooth_steps(steps: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Each parameter's steps, shrunk toward their robust mean.

    A lens breathes smoothly with the focus: neighbouring steps are nearly equal. Where ECC
    settles on a wrong step between two featureless frames (blurred, noisy: a bias its
    variance does not show), the chain would carry the error to every frame beyond; such a
    step gives way to the others' mean. Per parameter: the weighted mean (weights
    ``1 / (var + tau2)`` times Tukey's biweight of the standardised residual, 4.685), ``tau2``
    the scatter of the steps beyond their variances (median-based: a few wild steps do not
    set it), then each step's inverse-variance mean with the robust mean, its weight times
    its biweight. A lens whose steps really differ (uneven focus steps) has a large ``tau2``
    and keeps its well-measured steps.
    """
    out = steps.copy()
    for p in range(steps.shape[1]):
        y, v = steps[:, p], var[:, p]
        fin = np.isfinite(v)
        if fin.sum() < 4:
            continue
        vf = np.where(fin, v, np.inf)
        tau2, bw, mean = 0.0, fin.astype(np.float64), float(np.median(y[fin]))
        for _ in range(6):
            wts = bw / (vf + tau2 + 1e-30)
            mean = float(np.sum(wts * y) / np.sum(wts)) if wts.sum() > 0 else mean
            r2 = (y - mean) ** 2
            tau2 = max(0.0, float(np.median(r2[fin] - v[fin])) / 0.455)  # chi2(1) median
            bw = np.clip(1.0 - r2 / ((vf + tau2 + 1e-30) * 4.685**2), 0.0, None) ** 2
        if tau2 == 0.0:
            out[:, p] = mean
        else:
            wm = bw / vf  # a wild step (biweight 0): the mean
            out[:, p] = (wm * y + mean / tau2) / (wm + 1.0 / tau2)
    return out


def _chain_steps(steps: np.ndarray, ref: int, shape: tuple[int, int]) -> list[np.ndarray]:
    """Reference px -> frame k px (3 x 3) from the steps frame k - 1 -> k (``steps[k - 1]``)."""
    h, w = shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])

    def mat(step: np.ndarray) -> np.ndarray:
        s = math.exp(step[0])
        return np.array([[s, 0.0, c[0] - s * c[0] + step[1]],
                         [0.0, s, c[1] - s * c[1] + step[2]], [0.0, 0.0, 1.0]])

    n = steps.shape[0] + 1
    full = [np.eye(3) for _ in range(n)]
    for k in range(ref + 1, n):
        full[k] = mat(steps[k - 1]) @ full[k - 1]
    for k in range(ref - 1, -1, -1):
        full[k] = np.linalg.inv(mat(steps[k])) @ full[k + 1]
    return full


def align_stack(stack: np.ndarray, *, model: Model = "scale", reference: int | None = None,
                alignment: Alignment | None = None, aperture: bool = True
                ) -> tuple[np.ndarray, np.ndarray, Alignment]:
    """Warp every frame of a focus stack onto the reference frame's grid.

    Parameters
    ----------
    stack : (N, H, W) array of uint8, uint16 or float
    model, reference : as in :func:`estimate_alignment`.
    alignment : Alignment, optional
        Transforms already estimated (e.g. from a calibration); default estimated here.
    aperture : bool
        Give every frame the reference pixel's aperture (:func:`warp_frame`): without it a
        focus measure favours the magnified frames (measured: bench/align_families_results.md).

    Returns
    -------
    aligned : (N, H, W) array, ``stack``'s dtype
    valid : (H, W) bool
        Pixels that every frame covers (inside its border by the interpolation's reach:
        :data:`~sffscan.stages.fields.resample.TAPS` px, 3 px for Lanczos); the others hold
        replicated borders and must not be measured.
    alignment : Alignment
    """
    st = np.asarray(stack)
    al = alignment if alignment is not None else estimate_alignment(st, model=model,
                                                                    reference=reference)
    if al.matrices.shape[0] != st.shape[0]:
        raise ValueError(f"alignment has {al.matrices.shape[0]} transforms for "
                         f"{st.shape[0]} frames")
    out = np.empty_like(st)
    valid = np.ones(st.shape[1:], dtype=bool)
    for k in range(st.shape[0]):
        out[k] = warp_frame(st[k], al.matrices[k], aperture=aperture)
        reach = float(TAPS) if is_separable(al.matrices[k]) else 3.0
        valid &= coverage(al.matrices[k], st.shape[1:], reach)
    return out, valid, al


def misalignment(stack: np.ndarray) -> tuple[float, float]:
    """How misaligned a stack looks: the largest relative scale change (fraction) and shift
    (px) of its first and last frames against the middle one, at most 512 px wide.

    (0, 0) for stacks of fewer than 3 frames; (nan, nan) when ECC cannot align a pair.
    """
    st = np.asarray(stack)
    n = st.shape[0]
    if n < 3:
        return 0.0, 0.0
    f = max(1, int(math.ceil(max(st.shape[1:]) / 512)))
    def small(i: int) -> np.ndarray:
        img = to_float(st[i])
        return img if f == 1 else cv2.resize(img, (img.shape[1] // f, img.shape[0] // f),
                                              interpolation=cv2.INTER_AREA)
    try:
        # the frames as taken: the check was measured so (registration_frame's window is
        # in px of the full frames, these are up to 4x smaller)
        al = estimate_alignment(np.stack([small(0), small(n // 2), small(n - 1)]),
                                normalise=False)
    except ValueError:
        return math.nan, math.nan
    return (float(np.max(np.abs(al.scale - 1.0))),
            float(np.max(np.hypot(al.shift_px[:, 0], al.shift_px[:, 1]))) * f)


def describe_alignment(al: Alignment) -> str:
    """One line per frame: scale (and its change from the previous frame), shift, rotation."""
    lines = [f"alignment ({al.model}, reference frame {al.reference}): scale relative to the "
             "reference, change from the previous frame, shift of the centre"]
    for k in range(al.scale.size):
        step = "" if k == 0 else f" ({100 * (al.scale[k] / al.scale[k - 1] - 1):+.3f} %/frame)"
        rot = f", rotation {al.rotation_deg[k]:+.3f}°" if al.model != "scale" else ""
        lines.append(f"  frame {k:3d}: scale {al.scale[k]:.5f}{step}, shift "
                     f"({al.shift_px[k, 0]:+.2f}, {al.shift_px[k, 1]:+.2f}) px{rot}, "
                     f"ECC r {al.correlation[k]:.4f}")
    drift = al.shift_px[-1] - al.shift_px[0]
    lines.append(f"  the centre's shift from the first frame to the last: ({drift[0]:+.2f}, "
                 f"{drift[1]:+.2f}) px")
    if math.hypot(*drift) >= DRIFT_NOTE_PX:
        lines.append("  a drift like this is what a lens breathing about an off-centre axis "
                     "shows, and what a tilted part's blurred features show as the focus "
                     "moves: alignment cannot tell the two apart (docs/limits.md); on a "
                     "tilted part, measure the breathing on a flat checkerboard instead "
                     "(`sffscan calibrate lateral`, then `--calibration`)")
    return "\n".join(lines)


def check_alignment(stack: np.ndarray, *, tolerance_px: float = 1.0) -> bool:
    """Warn (logging) when a stack looks misaligned; True when it does.

    Misaligned: the first or last frame, against the middle one, is scaled or shifted by
    more than ``tolerance_px`` at the frame corner (:func:`misalignment`).
    """
    st = np.asarray(stack)
    h, w = st.shape[1:]
    scale, shift = misalignment(st)
    if math.isnan(scale):
        log.warning("could not check the stack's alignment (ECC did not converge between its "
                    "first, middle and last frames)")
        return False
    corner = scale * math.hypot(w / 2.0, h / 2.0)
    if max(corner, shift) > tolerance_px:
        log.warning(f"the stack looks misaligned: its end frames are scaled by up to "
                    f"{100 * scale:.2f} % ({corner:.1f} px at the corner) and shifted by "
                    f"{shift:.1f} px against the middle frame (focus breathing?); heights "
                    "along edges will be wrong: use --align")
        return True
    return False


def mask_uncovered(height_um: np.ndarray, valid: np.ndarray, *, reach_px: int) -> np.ndarray:
    """Height map with NaN where an aligned frame did not cover the pixel or its focus window.

    ``valid`` from :func:`align_stack`, shrunk by ``reach_px`` (the focus measure's reach);
    returns a float32 copy.
    """
    ok: np.ndarray = np.asarray(valid, dtype=np.uint8)
    if reach_px > 0:
        ok = cv2.erode(ok, np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=1)
    out = np.array(height_um, dtype=np.float32, copy=True)
    out[ok == 0] = np.nan
    return out


def prepare_stack(stack: np.ndarray, *, align: bool, model: Model = "scale"
                  ) -> tuple[np.ndarray, np.ndarray | None, Alignment | None]:
    """What ``sffscan stack`` does before the focus measure.

    With ``align``: :func:`align_stack` (returns the aligned stack, its ``valid`` mask and
    the :class:`Alignment`). Without: the stack unchanged, after :func:`check_alignment`
    (a warning when it looks misaligned), and ``None, None``.
    """
    if not align:
        check_alignment(stack)
        return np.asarray(stack), None, None
    return align_stack(stack, model=model)
