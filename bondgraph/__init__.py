"""bondgraph: declare -> causality -> equations -> codegen -> model -> simulate / filter /
estimate -> diagnose."""

from .errors import *  # noqa: F401,F403
from .symbols import Input, Parameter, StateVar, Var  # noqa: F401
from .elements import (C, CField, GY, I, IField, MGY, MTF, One, R, RField, Se, Sf, TF,  # noqa: F401
                       Zero)
from .graph import Bond, BondGraph, Fragment, Handle, Sensor  # noqa: F401
from .causality import Causality, assign_causality  # noqa: F401
from .equations import StateSpace, derive  # noqa: F401
from . import smooth  # noqa: F401

__version__ = "0.1.0"
