"""The focus measure operators of Pertuz's "Shape from focus" toolbox (``focusmeasure.m``).

:data:`FOCUS_OPERATORS` is the one registry of operators: name (the toolbox's acronym in
lower case) -> :class:`FocusOperator`, which says how far the operator reaches into the
image border, on which grid a crop must start, and where its code is. Each operator has
one definition, in torch, on ``(B, H, W)`` tensors of any device and dtype
(:mod:`.toolbox`, on the MATLAB-border filters of :mod:`.filters`; the wavelet operators in
:mod:`.wavelets`). GLVM and TENV, the two the scan uses most, also have an OpenCV CPU
front end with the same definition (:mod:`.opencv`). The thin front ends that check
inputs and move arrays are :func:`sffscan.stages.focus_measure.focus_measure` (numpy) and
:mod:`sffscan.stages.focus_torch` (torch tensors, devices).

Importing this package root loads neither torch nor OpenCV (nor numpy): the configuration
derives its list of choices from :data:`FOCUS_OPERATORS` without them. Names are case-insensitive
(``"LAPM"``, ``"lapm"``, see :func:`check_operator`). ``"tenv_std"`` is the thesis' form
of TENV (the local standard deviation of the Sobel energy instead of its variance).

The wavelet operators WAVS, WAVV and WAVR decimate: a crop gives the whole image's values
beyond :func:`operator_reach` only if it starts at a multiple of
:func:`operator_alignment` (2 or 8 px); every other operator has alignment 1.

Left out: those outside the issue's list (HISV, which the toolbox itself does not
implement; GRA3 and LAP3, which work across the stack; LBPA and WAVC, which need
third-party MATLAB code).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from importlib import import_module
from types import MappingProxyType
from typing import Any

__all__ = ["FOCUS_OPERATORS", "FocusOperator", "OperatorRegistry", "check_operator", "check_window",
           "operator_alignment", "operator_reach"]


@dataclass(frozen=True)
class FocusOperator:
    """One focus measure operator: its reach, its grid and where its code lives.

    Attributes
    ----------
    name : str
        The toolbox's acronym, lower case (``"glvm"``).
    first_reach : int or None
        How far beyond the window's half width ``r = k // 2`` the operator reads, px: the
        reach of the first filter for operators that box-average a per-pixel value
        (3 x 3 kernels: 1; the 4 x 4 correlation: 2; the 8 x 8 DCT windows: 4; Brenner
        and Vollath: 2; the wavelets: the db6 filters' 11 px per level, ``11 (2^L - 1)``
        for level L, measured on pertuz-simu02: 10 and at most 65). None for those that
        filter twice with k x k windows (reach ``2 r``).
    alignment : int
        The step, px, at which a crop must start for its result to equal the whole
        image's: ``2^L`` for the wavelet operators (level L), else 1.
    module : str
        The module of :mod:`sffscan.stages.operators` that holds the torch definition, a
        function named like the operator, ``f(x, k)`` on ``(B, H, W)`` tensors.
    opencv : str or None
        The OpenCV CPU front end in :mod:`.opencv`, ``f(image, *, window)`` on 2-D
        float32 arrays, or None (the CPU runs the torch definition).
    """

    name: str
    first_reach: int | None
    alignment: int = 1
    module: str = "toolbox"
    opencv: str | None = None

    def reach(self, window: int) -> int:
        """How far the image border reaches into the result, px, for window ``k``."""
        r = window // 2
        return 2 * r if self.first_reach is None else r + self.first_reach

    def torch_function(self) -> Callable[..., Any]:
        """The torch definition ``f(x, k)``: ``(B, H, W)`` tensor in, same shape, device and
        dtype out. Imports torch."""
        return getattr(import_module(f"{__name__}.{self.module}"), self.name)  # type: ignore[no-any-return]

    def opencv_function(self) -> Callable[..., Any] | None:
        """The OpenCV front end ``f(image, *, window)`` (2-D float32 in and out), or None."""
        if self.opencv is None:
            return None
        return getattr(import_module(f"{__name__}.opencv"), self.opencv)  # type: ignore[no-any-return]


class OperatorRegistry(Mapping[str, FocusOperator]):
    """Read-only mapping of name -> :class:`FocusOperator`, in the order given; its repr is
    the tuple of names (what error messages show as the choices)."""

    def __init__(self, *ops: FocusOperator) -> None:
        self._ops = MappingProxyType({op.name: op for op in ops})

    def __getitem__(self, name: str) -> FocusOperator:
        return self._ops[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._ops)

    def __len__(self) -> int:
        return len(self._ops)

    def __repr__(self) -> str:
        return repr(tuple(self._ops))


_Op = FocusOperator
FOCUS_OPERATORS = OperatorRegistry(
    _Op("acmo", None), _Op("bren", 2), _Op("cheb", None), _Op("cont", 1), _Op("curv", 1),
    _Op("dcte", 4), _Op("dctm", 2), _Op("dctr", 4), _Op("eigv", None), _Op("gder", None),
    _Op("gllv", None), _Op("glva", None), _Op("glvm", None, opencv="glvm_cv"),
    _Op("glvn", 0), _Op("grae", 1), _Op("gras", 1), _Op("grat", 1), _Op("helm", None),
    _Op("hise", None), _Op("hisr", None), _Op("lapd", 1), _Op("lape", 1), _Op("lapm", 1),
    _Op("lapv", 1), _Op("sfil", None), _Op("sfrq", 1), _Op("teng", 1),
    _Op("tenv", 1, opencv="tenv_cv"), _Op("tenv_std", 1), _Op("vola", 2), _Op("vols", None),
    _Op("wavr", 77, alignment=8, module="wavelets"),
    _Op("wavs", 11, alignment=2, module="wavelets"),
    _Op("wavv", 11, alignment=2, module="wavelets"),
)
"""Every focus operator, by lower-case name, in alphabetical order (read-only).

``tuple(FOCUS_OPERATORS)`` is the list of choices (configuration, command line)."""


def check_operator(operator: str) -> str:
    """The operator's lower-case name; ValueError naming the choices if it is unknown."""
    if not isinstance(operator, str) or operator.lower() not in FOCUS_OPERATORS:
        raise ValueError(f"operator must be one of {', '.join(FOCUS_OPERATORS)} (any case), "
                         f"got {operator!r}")
    return operator.lower()


def check_window(window: int) -> int:
    """The focus window k as an int: an odd integer >= 3, px; else ValueError naming it."""
    from sffscan.stages.depth_levels import check_odd_size  # numpy: this root stays light

    return check_odd_size(window, name="window", minimum=3)


def operator_reach(operator: str, window: int) -> int:
    """How far the image border reaches into the operator's result, px.

    A pixel closer than this to the border sees the padding (replicated, mirrored or zero,
    as MATLAB pads for that operator); farther in, the result equals the whole image's.
    """
    return FOCUS_OPERATORS[check_operator(operator)].reach(window)


def operator_alignment(operator: str) -> int:
    """The step, px, at which a crop must start for its result to equal the whole image's
    beyond :func:`operator_reach`: ``2^L`` for the wavelet operators (level L), else 1."""
    return FOCUS_OPERATORS[check_operator(operator)].alignment
