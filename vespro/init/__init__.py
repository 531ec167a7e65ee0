"""Automatic pose initialisation from images (see :mod:`vespro.init.initializer`).

The initialiser's names load on first use: the tracker imports the camera and model
helpers of this package (:mod:`vespro.init.features`, :mod:`vespro.init.modelfeat`)
without the hypothesis search, and :mod:`vespro.edgefit`, which the search imports,
imports those helpers in turn.
"""

import importlib

__all__ = ["InitOptions", "InitReport", "InitResult", "InitSetup", "Initializer", "decision_options", "initialize",
           "make_initializer", "make_setup"]


def __getattr__(name: str):
    if name in __all__:
        return getattr(importlib.import_module(".initializer", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
