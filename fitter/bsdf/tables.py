"""The README parameter tables, written from the lobes' ``doc``, ``Param`` and ``Option``.

``tests/test_bsdf_properties.py`` checks that README.md and configs/README.md
hold exactly these rows; ``python -m fitter.bsdf.tables`` prints them to paste.
"""

from __future__ import annotations

from typing import Iterable

from .base import Lobe, Option, Param


def number(v: float) -> str:
    """1e-3 and 1e4 rather than 0.001 and 10000; %g otherwise."""
    v = float(v)
    if v != 0 and (abs(v) >= 1e4 or abs(v) < 1e-2):
        mant, exp = f"{v:e}".split("e")
        return f"{mant.rstrip('0').rstrip('.')}e{int(exp)}"
    return f"{v:g}"


def toml(v) -> str:
    """An option value as written in a config."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return str(v)


def _box(p: Param) -> str:
    return f"[{number(p.lower)}, {number(p.upper)}]"


def _meaning(p: Param) -> str:
    if p.free:
        return p.doc
    return f"{p.doc}; fixed at {number(p.default)} unless given in `[material.init]`"


def _option_summary(o: Option) -> str:
    if o.choices is None:
        return f"option `{o.name}` = `{toml(o.default)}` (default)"
    values = " / ".join(f"`{toml(c)}`" + (" (default)" if c == o.default else "")
                        for c in o.choices)
    return f"option `{o.name}` = {values}"


def lobe_rows(lobes: Iterable[Lobe]) -> list[str]:
    """README.md, "The physics": | lobe | parameters (valid box) | model |."""
    rows = []
    for lobe in lobes:
        params = ", ".join(f"`{p.name}`" + (" RGB" if p.size == 3 else "") + f" {_box(p)}"
                           + ("" if p.free else " (fixed by default)") for p in lobe.params)
        options = "; ".join(_option_summary(o) for o in lobe.options)
        cell = params + (f"; {options}" if options else "")
        rows.append(f"| `{lobe.name}` | {cell} | {lobe.doc} |")
    return rows


def param_rows(lobes: Iterable[Lobe]) -> list[str]:
    """configs/README.md: | key | size | default | valid box | meaning |."""
    return [f"| `{lobe.name}.{p.name}` | {'RGB' if p.size == 3 else p.size} | "
            f"{number(p.default)} | {_box(p)} | {_meaning(p)} |"
            for lobe in lobes for p in lobe.params]


def option_rows(lobes: Iterable[Lobe]) -> list[str]:
    """configs/README.md: | key | values | default | meaning |."""
    rows = []
    for lobe in lobes:
        for o in lobe.options:
            values = ("int ≥ 0" if o.choices is None
                      else r" \| ".join(f"`{toml(c)}`" for c in o.choices))
            rows.append(f"| `{lobe.name}.{o.name}` | {values} | `{toml(o.default)}` | {o.doc} |")
    return rows


if __name__ == "__main__":
    from .registry import LOBES

    for title, rows in (("README.md", lobe_rows(LOBES.values())),
                        ("configs/README.md parameters", param_rows(LOBES.values())),
                        ("configs/README.md options", option_rows(LOBES.values()))):
        print(f"{title}:\n" + "\n".join(rows) + "\n")
