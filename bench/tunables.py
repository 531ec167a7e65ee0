"""The settings of the estimation path: every field of its ``*Options`` / ``*Config`` / ``*Params``
dataclasses and the edge aid's parameters, counted.

Walks the modules of ``vespro`` that take part in estimating a pose (not the
simulator, the servo, the commands or calibration) and prints one row per
settings class with its number of fields, and the total.

Usage: ``python3 bench/tunables.py [--names]``
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import pkgutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import vespro  # noqa: E402

#: Modules outside the estimation path.
OUTSIDE = ("vespro.sim", "vespro.calib", "vespro.cmd_", "vespro.cli", "vespro.__main__",
           "vespro.warmup", "vespro.viewer", "vespro.mcap_export", "vespro.ros2", "vespro.zenoh_link", "vespro.link",
           "vespro.wire", "vespro.server", "vespro.sources", "vespro.loadshed", "vespro.suite", "vespro.bop",
           "vespro.evaluate", "vespro.library", "vespro.toy_scene", "vespro.realtime", "vespro.throttle")
SUFFIXES = ("Options", "Config", "Params")


def settings_classes() -> list[tuple[str, type, list[str]]]:
    """(module, class, field names) of every settings dataclass in the estimation path."""
    out, seen = [], set()
    for info in pkgutil.walk_packages(vespro.__path__, "vespro."):
        if info.name.startswith(OUTSIDE):
            continue
        mod = importlib.import_module(info.name)
        for name, cls in inspect.getmembers(mod, inspect.isclass):
            if cls.__module__ != info.name or cls in seen:
                continue
            if dataclasses.is_dataclass(cls) and name.endswith(SUFFIXES):
                seen.add(cls)
                out.append((info.name, cls, [f.name for f in dataclasses.fields(cls)]))
    from vespro.edgeaid import EdgeAid

    params = [p for p in inspect.signature(EdgeAid.__init__).parameters.values()
              if p.default is not inspect.Parameter.empty and p.name != "tree"]  # (the BSP tree: data)
    out.append(("vespro.edgeaid", EdgeAid, [p.name for p in params]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--names", action="store_true", help="list the fields too")
    a = ap.parse_args(argv)
    rows = settings_classes()
    w = max(len(f"{m}.{c.__name__}") for m, c, _ in rows)
    print(f"{'settings':<{w}}  fields")
    print("-" * (w + 8))
    for m, c, names in rows:
        print(f"{m + '.' + c.__name__:<{w}}  {len(names):6d}" + (f"  {' '.join(names)}" if a.names else ""))
    print("-" * (w + 8))
    print(f"{'total':<{w}}  {sum(len(n) for *_, n in rows):6d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
