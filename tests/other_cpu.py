"""Make this machine compute as another CPU would, to test results that must not depend on the CPU.

    python tests/other_cpu.py PROFILE -- COMMAND...     run COMMAND with PROFILE's settings
    python tests/other_cpu.py PROFILE                   print them (KEY=VALUE lines)

Three libraries choose their kernels by CPU at run time, and each can be told not to:

* numpy: ``NPY_DISABLE_CPU_FEATURES`` switches off dispatch targets.  It must name targets this numpy
  was built with and this CPU has (numpy 2.4 calls them X86_V3, X86_V4, AVX512_ICL, ...; older ones
  AVX2, AVX512F, AVX512_SKX, ...): other names are ignored without a word, so the list is read off
  numpy's own tables here;
* OpenBLAS: ``OPENBLAS_CORETYPE`` picks a kernel set (Nehalem: SSE only, no fused multiply-add;
  Haswell: AVX2 and FMA);
* glibc's libm (``exp``, ``expm1`` and others have FMA/AVX2 variants): ``GLIBC_TUNABLES`` masks CPU
  features (both spellings, before and after glibc 2.33, are given; unknown ones are ignored).

Profiles:

* ``generic``: every numpy dispatch target off (numpy's baseline code), OpenBLAS Nehalem, libm without
  AVX-512, AVX2 or FMA: an old x86-64 without AVX;
* ``avx2``: numpy's AVX-512 targets off, OpenBLAS Haswell, libm without AVX-512: a CPU with AVX2 but
  no AVX-512 (such as the AMD EPYC machine that first showed the golden file failing elsewhere).

On a CPU that lacks a feature the profile would switch off, that part changes nothing (the machine
already is that CPU).
"""

from __future__ import annotations

import os
import sys

_GLIBC_MASKS = {"generic": ("AVX512F", "AVX2", "FMA"), "avx2": ("AVX512F",)}
_OPENBLAS = {"generic": "Nehalem", "avx2": "Haswell"}
PROFILES = tuple(_OPENBLAS)


def numpy_dispatch_targets_on() -> list[str]:
    """The dispatch targets this numpy was built with that this CPU has (numpy >= 1.20)."""
    try:
        from numpy._core import _multiarray_umath as umath  # numpy >= 2
    except ImportError:
        from numpy.core import _multiarray_umath as umath  # numpy 1.x
    features = umath.__cpu_features__
    return [name for name in umath.__cpu_dispatch__ if features.get(name)]


def _is_avx512(name: str) -> bool:
    return "AVX512" in name or name == "X86_V4"


def environment(profile: str) -> dict[str, str]:
    """The variables that make numpy, OpenBLAS and libm compute as ``profile``'s CPU."""
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r} (known: {', '.join(PROFILES)})")
    targets = numpy_dispatch_targets_on()
    disabled = targets if profile == "generic" else [t for t in targets if _is_avx512(t)]
    masks = _GLIBC_MASKS[profile]
    hwcaps = ",".join([f"-{m}" for m in masks] + [f"-{m}_Usable" for m in masks])
    env = {"OPENBLAS_CORETYPE": _OPENBLAS[profile], "GLIBC_TUNABLES": f"glibc.cpu.hwcaps={hwcaps}"}
    if disabled:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(disabled)
    return env


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in PROFILES or (len(argv) > 1 and (argv[1] != "--" or len(argv) < 3)):
        print(f"usage: python tests/other_cpu.py {{{','.join(PROFILES)}}} [-- COMMAND...]", file=sys.stderr)
        return 2
    env = environment(argv[0])
    if len(argv) == 1:
        for key, value in env.items():
            print(f"{key}={value}")
        return 0
    print(f"as another CPU ({argv[0]}): " + " ".join(f"{k}='{v}'" for k, v in env.items()), file=sys.stderr, flush=True)
    os.execvpe(argv[2], argv[2:], {**os.environ, **env})


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
