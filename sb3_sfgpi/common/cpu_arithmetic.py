"""One code path for torch's matrix products on every Intel CPU, so that a seeded deep run gives the same numbers.

Torch's x86 builds hand float matrix products to Intel's MKL, which picks its kernels at its first call from the CPU's
instruction set. AVX-512 and AVX2 kernels add in different orders, so a deep learner's seeded run left the last bit
at its first update and went elsewhere from there: 1,500 steps of the deep preset on minecart-deterministic ended at
−0.3116 on an AVX-512 Xeon and at −0.8636 with MKL held to its AVX2 kernels on the same machine. MKL's conditional
numerical reproducibility (the ``MKL_CBWR`` environment variable) fixes the code path: :data:`MKL_CODE_PATH` runs on
every Intel CPU with AVX2 (since 2013) and gives the same bits whatever the number of threads.

MKL takes Intel's named code paths on Intel CPUs only: on an AMD CPU it keeps its automatic choice, in the strict mode
asked for (``AUTO,STRICT``): a seeded run gives the same bits on that CPU for any number of threads, and other numbers
than an Intel CPU's. ``MKL_CBWR=COMPATIBLE`` (SSE2 kernels, the same bits on both as MKL documents it) costs about
1.3 times the CPU time of a deep run; the package does not ask for it but keeps it where the user sets it, and
``software.json`` records the path a run took.

MKL reads the variable once, at its first call, so ``import sb3_sfgpi`` sets it (where the user has not) before
anything of the package runs; a process whose torch multiplied matrices before that keeps the CPU's own kernels, and
its deep learners say so (:func:`warn_unless_pinned`). Tabular learners never call MKL (:mod:`sb3_sfgpi.common.weights`
is how their sums stay in one order), and CUDA's arithmetic is the card's: ``software.json`` names the card.
"""

from __future__ import annotations

import ctypes
import os
import sys
import warnings
from pathlib import Path

#: The MKL code path every run takes: AVX2's kernels, the same bits for any number of threads.
MKL_CODE_PATH = "AVX2,STRICT"

#: MKL's codes for its code paths (``mkl_service.h``); ``MKL_CBWR_BRANCH_OFF`` (1) is the CPU's own kernels.
_BRANCHES = {1: "the CPU's own", 2: "AUTO", 3: "COMPATIBLE", 4: "SSE2", 6: "SSSE3", 7: "SSE4_1", 8: "SSE4_2"}
_BRANCHES.update({9: "AVX", 10: "AVX2", 11: "AVX512_MIC", 12: "AVX512", 13: "AVX512_MIC_E1", 14: "AVX512_E1"})
_STRICT = 0x10000  # MKL_CBWR_STRICT
_ALL = -1  # MKL_CBWR_ALL: the branch and the STRICT flag


def pin_mkl_code_path() -> None:
    """Ask MKL for :data:`MKL_CODE_PATH`, unless the user set ``MKL_CBWR`` (a no-op once MKL has run)."""
    os.environ.setdefault("MKL_CBWR", MKL_CODE_PATH)


def mkl_code_path() -> str | None:
    """
    The code path torch's MKL takes, as MKL reports it.

    :return: e.g. ``"AVX2,STRICT"`` or ``"the CPU's own"``; ``None`` where torch is not imported or has no MKL (ARM,
        macOS, a build that does not export MKL's service functions)
    """
    torch = sys.modules.get("torch")
    if torch is None or torch.__file__ is None:
        return None
    try:
        get = ctypes.CDLL(str(Path(torch.__file__).parent / "lib" / "libtorch_cpu.so")).mkl_serv_cbwr_get
    except (OSError, AttributeError):  # no such library (macOS, Windows), or one without MKL (ARM)
        return None
    get.restype, get.argtypes = ctypes.c_int, [ctypes.c_int]
    mode = get(_ALL)
    name = _BRANCHES.get(mode & ~_STRICT, f"code {mode & ~_STRICT}")
    return f"{name},STRICT" if mode & _STRICT else name


def warn_unless_pinned() -> None:
    """
    Warn when MKL runs the CPU's own kernels though :data:`MKL_CODE_PATH` was asked for: it ran before the ask.

    Any strict path is what the ask gave (an AMD CPU's is ``AUTO,STRICT``); without ``STRICT`` MKL never read it.
    """
    path = mkl_code_path()
    if path is not None and not path.endswith(",STRICT") and os.environ.get("MKL_CBWR") == MKL_CODE_PATH:
        warnings.warn(
            f"torch's MKL runs {path} kernels, not {MKL_CODE_PATH}: torch multiplied matrices before sb3_sfgpi was "
            "imported, so this deep run's numbers are this CPU's; import sb3_sfgpi first, or set "
            f"MKL_CBWR={MKL_CODE_PATH} in the environment",
            stacklevel=3,
        )
