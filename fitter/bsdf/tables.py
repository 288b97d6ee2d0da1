"""The README parameter tables, written from the lobes' ``doc``, ``Param`` and ``Option``.

``tests/test_bsdf_properties.py`` checks that README.md and configs/README.md
hold exactly these rows; ``python -m fitter.bsdf.tables`` prints them,
``python -m fitter.bsdf.tables --write`` rewrites them in place.
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


def _variant_params(lobe: Lobe):
    """((option, value), params that differ from the default ones) per variant."""
    return [((name, value), [p for p in params if p not in lobe.params])
            for (name, value), params in lobe.variants.items()]


def lobe_rows(lobes: Iterable[Lobe]) -> list[str]:
    """README.md, "The physics": | lobe | parameters (valid box) | model |."""
    rows = []
    for lobe in lobes:
        show = lambda ps: ", ".join(  # noqa: E731
            f"`{p.name}`" + (" RGB" if p.size == 3 else "") + f" {_box(p)}"
            + ("" if p.free else " (fixed by default)") for p in ps)
        params = show(lobe.params)
        for (name, value), ps in _variant_params(lobe):
            params += f"; with `{name}` = `{toml(value)}`: {show(ps)}"
        options = "; ".join(_option_summary(o) for o in lobe.options)
        cell = params + (f"; {options}" if options else "")
        rows.append(f"| `{lobe.name}` | {cell} | {lobe.doc} |")
    return rows


def param_rows(lobes: Iterable[Lobe]) -> list[str]:
    """configs/README.md: | key | size | default | valid box | meaning |."""
    row = lambda lobe, p, when="": (  # noqa: E731
        f"| `{lobe.name}.{p.name}`{when} | {'RGB' if p.size == 3 else p.size} | "
        f"{number(p.default)} | {_box(p)} | {_meaning(p)} |")
    rows = []
    for lobe in lobes:
        rows += [row(lobe, p) for p in lobe.params]
        for (name, value), ps in _variant_params(lobe):
            rows += [row(lobe, p, f" (`{name}` = `{toml(value)}`)") for p in ps]
    return rows


def option_rows(lobes: Iterable[Lobe]) -> list[str]:
    """configs/README.md: | key | values | default | meaning |."""
    rows = []
    for lobe in lobes:
        for o in lobe.options:
            values = ((f"int in [0, {o.most}]" if o.most is not None else "int ≥ 0")
                      if o.choices is None
                      else r" \| ".join(f"`{toml(c)}`" for c in o.choices))
            rows.append(f"| `{lobe.name}.{o.name}` | {values} | `{toml(o.default)}` | {o.doc} |")
    return rows


#: (file, header line of its table, rows function).
TABLES = (("README.md", "| lobe | parameters (valid box) | model |", lobe_rows),
          ("configs/README.md", "| key | size | default | valid box | meaning |", param_rows),
          ("configs/README.md", "| key | values | default | meaning |", option_rows))


def write(root: str) -> None:
    """Replace the body rows of each table in ``TABLES`` under ``root`` by the lobes' rows."""
    import os

    from .registry import LOBES

    for name, header, rows in TABLES:
        path = os.path.join(root, name)
        with open(path, encoding="utf-8") as fh:
            lines = fh.read().split("\n")
        start = lines.index(header) + 2  # header, |---|
        end = start
        while end < len(lines) and lines[end].startswith("|"):
            end += 1
        lines[start:end] = rows(LOBES.values())
        with open(path, "w", encoding="utf-8") as fh:
            fh.write("\n".join(lines))


if __name__ == "__main__":
    import sys

    from .registry import LOBES

    if sys.argv[1:2] == ["--write"]:  # python -m fitter.bsdf.tables --write [ROOT]
        write(sys.argv[2] if len(sys.argv) > 2 else ".")
    else:
        for name, header, rows in TABLES:
            print(f"{name} {header}:\n" + "\n".join(rows(LOBES.values())) + "\n")
