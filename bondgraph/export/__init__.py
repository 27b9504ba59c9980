"""The identified model elsewhere (issue 31): a standalone FMI 2.0 FMU
(:mod:`bondgraph.export.fmu`) and the linearisation A, B, C, D at an
operating point (:mod:`bondgraph.export.linearize`)."""
