"""Automatic pose initialisation from images (see :mod:`vespro.init.initializer`)."""

from .initializer import (InitOptions, InitReport, InitResult, InitSetup, Initializer, initialize, make_initializer,
                          make_setup)

__all__ = ["InitOptions", "InitReport", "InitResult", "InitSetup", "Initializer", "initialize", "make_initializer",
           "make_setup"]
