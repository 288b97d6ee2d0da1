"""The lobe registry: name -> Lobe. Adding a lobe is one module + one line here.

Everything that needs a lobe (material, config validator, renderer, Mitsuba
translation, tests) looks it up in ``LOBES`` when used, so ``registered``
can add a lobe for a block of code (a throwaway lobe in a test) and remove it
afterwards.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

from . import dielectric, lambert, mirror, oren_nayar, phong, torrance_sparrow
from .base import Lobe

LOBES: dict[str, Lobe] = {
    m.LOBE.name: m.LOBE
    for m in (lambert, oren_nayar, phong, torrance_sparrow, mirror, dielectric)
}

#: Lobes ``registered`` has removed again. Compiled renders are cached by the
#: material's lobe *names*, so a name may come back only as the same lobe.
_RETIRED: dict[str, Lobe] = {}


@contextlib.contextmanager
def registered(*lobes: Lobe) -> Iterator[dict[str, Lobe]]:
    """Add ``lobes`` to ``LOBES`` inside the ``with`` block only; yields ``LOBES``.

    Raises ValueError for a name already registered, or one used before by a
    different lobe (caches keyed by name would serve the old one).
    """
    for lobe in lobes:
        if lobe.name in LOBES:
            raise ValueError(f"lobe {lobe.name!r} is already registered")
        if _RETIRED.get(lobe.name, lobe) is not lobe:
            raise ValueError(f"lobe name {lobe.name!r} was used by another lobe in this "
                             "process; caches are keyed by name, pick a new one")
    if len({lb.name for lb in lobes}) != len(lobes):
        raise ValueError(f"duplicate lobe names in {[lb.name for lb in lobes]}")
    LOBES.update({lb.name: lb for lb in lobes})
    try:
        yield LOBES
    finally:
        for lobe in lobes:
            del LOBES[lobe.name]
            _RETIRED[lobe.name] = lobe
