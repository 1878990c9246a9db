"""The focus measure operators of Pertuz's "Shape from focus" toolbox (``focusmeasure.m``).

This package root is torch-free: names, how far each operator reaches into the image
border, and the name check. The torch implementations are in :mod:`.toolbox` (on top of
the MATLAB-border filters of :mod:`.filters`).

Operators are named by the toolbox's acronyms, case-insensitive (``"LAPM"``, ``"lapm"``);
:data:`OPERATORS` lists them in lower case. ``"tenv_std"`` is the thesis' form of TENV
(the local standard deviation of the Sobel energy instead of its variance).

The wavelet operators WAVS, WAVV and WAVR (:mod:`.wavelets`, through PyWavelets) decimate:
a crop gives the whole image's values beyond :func:`operator_reach` only if it starts at a
multiple of :func:`operator_alignment` (2 or 8 px); every other operator has alignment 1.

Left out: those outside the issue's list (HISV, which the toolbox itself does not
implement; GRA3 and LAP3, which work across the stack; LBPA and WAVC, which need
third-party MATLAB code).
"""

from __future__ import annotations

__all__ = ["OPERATORS", "check_operator", "operator_alignment", "operator_reach"]

OPERATORS = (
    "acmo", "bren", "cheb", "cont", "curv", "dcte", "dctm", "dctr", "eigv", "gder", "gllv",
    "glva", "glvm", "glvn", "grae", "gras", "grat", "helm", "hise", "hisr", "lapd", "lape",
    "lapm", "lapv", "sfil", "sfrq", "teng", "tenv", "tenv_std", "vola", "vols", "wavr", "wavs",
    "wavv",
)
"""Operator names (lower case; :func:`check_operator` accepts any case)."""

# How far beyond the window's half width r = k // 2 each operator reads, px: the first
# filter's reach (3 x 3 kernels: 1; 4 x 4 correlation: 2; the 8 x 8 DCT windows: 4;
# Brenner and Vollath: 2) for operators that box-average a per-pixel value; ``None`` for
# those that filter twice with k x k windows (reach 2r). The wavelet operators: the db6
# filters' 11 px per level, 11 (2^L - 1) for level L (measured on pertuz-simu02: 10 and
# at most 65).
_FIRST_REACH: dict[str, int | None] = {
    "acmo": None, "bren": 2, "cheb": None, "cont": 1, "curv": 1, "dcte": 4, "dctm": 2,
    "dctr": 4, "eigv": None, "gder": None, "gllv": None, "glva": None, "glvm": None,
    "glvn": 0, "grae": 1, "gras": 1, "grat": 1, "helm": None, "hise": None, "hisr": None,
    "lapd": 1, "lape": 1, "lapm": 1, "lapv": 1, "sfil": None, "sfrq": 1, "teng": 1,
    "tenv": 1, "tenv_std": 1, "vola": 2, "vols": None, "wavr": 77, "wavs": 11, "wavv": 11,
}
_ALIGNMENT = {"wavr": 8, "wavs": 2, "wavv": 2}  # 2^L, L the decomposition level


def check_operator(operator: str) -> str:
    """The operator's lower-case name; ValueError naming the choices if it is unknown."""
    name = operator.lower() if isinstance(operator, str) else operator
    if name not in OPERATORS:
        raise ValueError(f"operator must be one of {', '.join(OPERATORS)} (any case), "
                         f"got {operator!r}")
    return str(name)


def operator_reach(operator: str, window: int) -> int:
    """How far the image border reaches into the operator's result, px.

    A pixel closer than this to the border sees the padding (replicated, mirrored or zero,
    as MATLAB pads for that operator); farther in, the result equals the whole image's.
    """
    first = _FIRST_REACH[check_operator(operator)]
    r = window // 2
    return 2 * r if first is None else r + first


def operator_alignment(operator: str) -> int:
    """The step, px, at which a crop must start for its result to equal the whole image's
    beyond :func:`operator_reach`: ``2^L`` for the wavelet operators (level L), else 1."""
    return _ALIGNMENT.get(check_operator(operator), 1)
