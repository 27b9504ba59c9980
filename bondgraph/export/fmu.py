"""A standalone FMI 2.0 FMU (Model Exchange and Co-Simulation) of a model.

:func:`export_fmu` derives the model's state space, prints its C99
functions (:mod:`bondgraph.core.codegen_c`, the generator of
``generated/c/<model>.c``), writes ``modelDescription.xml``, compiles the
FMI functions (``fmi2/fmu.c`` beside this module, with the FMI 2.0 headers
copied from the standard, BSD-2) into ``binaries/<platform>/<id>.so`` with
the system C compiler and zips the lot with the sources. The FMU needs no
Python at run time.

FMI 2.0 rather than 3.0: every importer named in issue 31 (Simulink,
the Modelica tools, fmpy, 20-sim) reads 2.0, the one version with the
widest support; a bond graph's ODE needs nothing that 3.0 adds (arrays,
clocks, intermediate updates).

Variables (value references in this order): parameters
(``causality="parameter"``, ``variability="fixed"``, start = the estimate
or default), states (``local``, ``initial="exact"``, start = X0), their
derivatives ``der(<state>)``, inputs (``causality="input"``, start = the
input's default), outputs (``causality="output"``); each with its unit,
every unit defined in ``UnitDefinitions`` with its SI base-unit exponents
and factor (pint). Co-simulation holds the inputs constant over a
communication step and integrates with an embedded Dormand-Prince 5(4)
pair under the importer's relative tolerance (``fmi2/fmu.c``).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import subprocess
import tempfile
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping
from xml.etree import ElementTree as ET

from bondgraph.core import units
from bondgraph.core.codegen_c import generate_c_source
from bondgraph.core.domains import jump_laws
from bondgraph.core.equations import StateSpace, derive
from bondgraph.core.graph import BondGraph
from bondgraph.core.symbols import identifier
from bondgraph.errors import ExportError, OptionError, UnitMismatchError
from bondgraph.export.params import model_graph

#: folder of the fmi2 C functions and the FMI 2.0 headers
FMI2_DIR = Path(__file__).with_name("fmi2")
#: files of FMI2_DIR copied into the FMU's sources/
FMI2_FILES = ("fmu.c", "fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h",
              "LICENSE.txt")
#: compilers tried in order when $CC is not set
COMPILERS = ("cc", "gcc", "clang")


@dataclass(frozen=True)
class FMUOptions:
    """How an FMU is built.

    Parameters
    ----------
    compiler : str, optional
        C compiler (a name on PATH or a path); default ``$CC``, else the
        first of :data:`COMPILERS` found.
    tolerance : float
        Relative tolerance of the DefaultExperiment (the co-simulation
        integrator's tolerance when the importer gives none), in (0, 0.1).
    stop_time : float, optional
        Stop time [s] of the DefaultExperiment (> 0).

    Raises
    ------
    OptionError
        A tolerance or stop time out of range.
    """

    compiler: str | None = None
    tolerance: float = 1e-8
    stop_time: float | None = None

    def __post_init__(self):
        if not 0.0 < float(self.tolerance) < 0.1:
            raise OptionError(f"FMUOptions.tolerance must be in (0, 0.1), got {self.tolerance!r}")
        if self.stop_time is not None and not float(self.stop_time) > 0:
            raise OptionError(f"FMUOptions.stop_time must be > 0, got {self.stop_time!r}")


def find_compiler(compiler: str | None = None) -> str:
    """Path of the C compiler: ``compiler``, else ``$CC``, else the first of
    :data:`COMPILERS` on PATH.

    Raises
    ------
    ExportError
        No compiler found (what was looked for is named).
    """
    wanted = [compiler] if compiler else ([os.environ["CC"]] if os.environ.get("CC") else
                                          list(COMPILERS))
    for name in wanted:
        path = shutil.which(name)
        if path:
            return path
    raise ExportError(f"no C compiler found (looked for {', '.join(wanted)} on PATH); an FMU "
                      f"is compiled at export",
                      hint="install gcc or clang (e.g. `apt-get install gcc`), or name one "
                           "with --compiler or $CC")


def platform_folder() -> tuple[str, str]:
    """``(binaries folder, shared-library suffix)`` of this machine in FMI 2.0
    terms (``linux64``, ``darwin64``, ``win64``; 32-bit variants).

    Raises
    ------
    ExportError
        An operating system FMI 2.0 names no folder for.
    """
    bits = "64" if platform.architecture()[0] == "64bit" else "32"
    system = platform.system()
    if system == "Linux":
        return f"linux{bits}", ".so"
    if system == "Darwin":
        return f"darwin{bits}", ".dylib"
    if system == "Windows":
        return f"win{bits}", ".dll"
    raise ExportError(f"FMI 2.0 has no binaries folder for the operating system {system!r}")


def _step_hint(ss) -> str:
    """``#define BG_STEP_HINT "..."`` for config.h when the model has laws
    that jump (``sign(v)``, :data:`bondgraph.core.domains.JUMPS`): the
    co-simulation's adaptive Dormand-Prince step cannot cross a jump where a
    state sticks (Coulomb friction holding a mass), and its error then
    names the law; '' otherwise."""
    jumps = jump_laws(ss.domain_notes)
    if not jumps:
        return ""
    text = (f"; the model's {', '.join(jumps)} jumps at 0, and a state that sticks there makes "
            f"the derivative switch at every step: export a smooth law (tanh(x/eps)), or use "
            f"Model Exchange with a fixed-step solver")
    return f"#define BG_STEP_HINT {json.dumps(text)}\n"


def export_fmu(model: str | BondGraph, path: str | Path, *,
               params: Mapping[str, float] | None = None,
               options: FMUOptions = FMUOptions()) -> Path:
    """Write a standalone FMI 2.0 FMU (Model Exchange and Co-Simulation).

    Parameters
    ----------
    model : str or BondGraph
        Registered name, ``module:function``, ``path/to/file.py:function``
        (e.g. the loop's ``augmented_model.py:build``) or a graph.
    path : str or Path
        The ``.fmu`` file to write (its folder is created).
    params : mapping, optional
        Parameter values (model units), e.g.
        :func:`bondgraph.export.params.read_params` of a ``result.json``:
        the parameters' start values and the compiled defaults.
    options : FMUOptions

    Returns
    -------
    Path
        The FMU written.

    Raises
    ------
    ExportError
        No C compiler, a failed compile (the compiler's messages quoted),
        unknown parameters.
    ModelError
        Unknown model reference.

    Notes
    -----
    Follows the FMI 2.0 standard (Modelica Association 2014, *Functional
    Mock-up Interface for Model Exchange and Co-Simulation*, version 2.0):
    sections 2.2 (modelDescription.xml), 3 (Model Exchange) and 4
    (Co-Simulation).
    """
    cc = find_compiler(options.compiler)
    graph = model_graph(model, params)
    ss = derive(graph)
    c_source = generate_c_source(ss, source=graph.source or f"<graph {graph.name}>",
                                 command="bondgraph export")
    model_id = identifier(ss.name) or "model"
    guid = "{" + str(uuid.uuid5(uuid.NAMESPACE_URL, "bondgraph:" + hashlib.sha256(
        c_source.encode()).hexdigest())) + "}"
    folder, suffix = platform_folder()
    path = Path(path)
    with tempfile.TemporaryDirectory(prefix="bondgraph_fmu_") as tmp:
        root = Path(tmp)
        src = root / "sources"
        src.mkdir()
        for name in FMI2_FILES:
            shutil.copyfile(FMI2_DIR / name, src / name)
        (src / "model.c").write_text(c_source)
        (src / "config.h").write_text(f'#define BG_GUID "{guid}"\n' + _step_hint(ss))
        binary = root / "binaries" / folder / f"{model_id}{suffix}"
        binary.parent.mkdir(parents=True)
        _compile(cc, src / "fmu.c", binary)
        xml = model_description(ss, model_id=model_id, guid=guid, options=options)
        (root / "modelDescription.xml").write_bytes(xml)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp_fmu = path.with_name(path.name + ".part")
        with zipfile.ZipFile(tmp_fmu, "w", zipfile.ZIP_DEFLATED) as zf:
            for f in sorted(root.rglob("*")):
                if f.is_file():
                    zf.write(f, f.relative_to(root).as_posix())
        os.replace(tmp_fmu, path)
    return path


def _compile(cc: str, source: Path, binary: Path) -> None:
    """``cc -shared`` the fmi2 functions into ``binary``.

    Raises
    ------
    ExportError
        The compiler failed (its command and messages quoted).
    """
    cmd = [cc, "-std=c99", "-O2", "-shared", "-fPIC", "-fvisibility=default", "-I",
           str(source.parent), str(source), "-o", str(binary), "-lm"]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ExportError(f"the C compiler {cc} could not run: {exc}") from None
    if r.returncode != 0:
        raise ExportError(f"compiling the FMU failed ({' '.join(cmd)}):\n"
                          f"{(r.stderr or r.stdout).strip()[:4000]}")


def _unit_element(parent: ET.Element, unit: str) -> None:
    """A ``<Unit>`` with its ``<BaseUnit>`` (SI exponents and factor, by
    pint) when pint knows the unit, else the name alone."""
    el = ET.SubElement(parent, "Unit", name=unit)
    try:
        q = units.parse(unit).to_base_units()
    except (UnitMismatchError, Exception):   # pint raises several types
        return
    dims = {"[mass]": "kg", "[length]": "m", "[time]": "s", "[current]": "A",
            "[temperature]": "K", "[substance]": "mol", "[luminosity]": "cd"}
    attrs = {}
    for dim, exp in dict(q.dimensionality).items():
        if dim not in dims or int(exp) != exp:
            return
        attrs[dims[dim]] = str(int(exp))
    if float(q.magnitude) != 1.0:
        attrs["factor"] = repr(float(q.magnitude))
    ET.SubElement(el, "BaseUnit", attrs)


def _variable(parent, name, vr, causality, variability, *, initial=None, description="",
              unit="", start=None, derivative=None) -> None:
    """One ``<ScalarVariable>`` with its ``<Real>``."""
    attrs = {"name": name, "valueReference": str(vr), "causality": causality,
             "variability": variability}
    if initial:
        attrs["initial"] = initial
    if description:
        attrs["description"] = description
    sv = ET.SubElement(parent, "ScalarVariable", attrs)
    real = {}
    if unit:
        real["unit"] = unit
    if derivative is not None:
        real["derivative"] = str(derivative)
    if start is not None:
        real["start"] = repr(float(start))
    ET.SubElement(sv, "Real", real)


def _model_variables(root: ET.Element, ss: StateSpace) -> tuple[list[int], list[int]]:
    """``<ModelVariables>``; returns the 1-based indices of the derivatives
    and of the outputs."""
    mv = ET.SubElement(root, "ModelVariables")
    vr = 0
    for p in ss.params:
        _variable(mv, p.name, vr, "parameter", "fixed", initial="exact",
                  description=p.description, unit=p.unit or "", start=p.default)
        vr += 1
    first_state = vr + 1
    for s in ss.states:
        _variable(mv, s.name, vr, "local", "continuous", initial="exact",
                  description=f"{s.state_kind}{' of ' + s.element if s.element else ''}",
                  unit=s.unit or "", start=s.initial)
        vr += 1
    derivatives = []
    for i, s in enumerate(ss.states):
        _variable(mv, f"der({s.name})", vr, "local", "continuous",
                  description=f"time derivative of {s.name}", derivative=first_state + i)
        vr += 1
        derivatives.append(vr)
    for u in ss.inputs:
        _variable(mv, u.name, vr, "input", "continuous", description=u.description,
                  unit=u.unit or "", start=u.default)
        vr += 1
    outputs = []
    for o in ss.outputs:
        _variable(mv, o.name, vr, "output", "continuous", description=o.description,
                  unit=o.unit or "")
        vr += 1
        outputs.append(vr)
    return derivatives, outputs


def model_description(ss: StateSpace, *, model_id: str, guid: str,
                      options: FMUOptions = FMUOptions()) -> bytes:
    """``modelDescription.xml`` of the model (FMI 2.0, section 2.2).

    Parameters
    ----------
    ss : StateSpace
    model_id : str
        The modelIdentifier (a C identifier; the shared library's name).
    guid : str
        The GUID compiled into the binary.
    options : FMUOptions

    Returns
    -------
    bytes
        UTF-8 XML.
    """
    root = ET.Element("fmiModelDescription", {
        "fmiVersion": "2.0", "modelName": ss.name, "guid": guid,
        "description": (ss.description or "").strip(),
        "generationTool": "bondgraph (bondgraph export)",
        "variableNamingConvention": "flat", "numberOfEventIndicators": "0"})
    common = {"modelIdentifier": model_id, "canGetAndSetFMUstate": "false",
              "canSerializeFMUstate": "false", "providesDirectionalDerivative": "false"}
    for kind, extra in (("ModelExchange", {"completedIntegratorStepNotNeeded": "true"}),
                        ("CoSimulation", {"canHandleVariableCommunicationStepSize": "true"})):
        el = ET.SubElement(root, kind, {**common, **extra})
        ET.SubElement(ET.SubElement(el, "SourceFiles"), "File", name="fmu.c")
    used = sorted({v.unit for v in [*ss.params, *ss.states, *ss.inputs] if v.unit}
                  | {o.unit for o in ss.outputs if o.unit})
    if used:
        ud = ET.SubElement(root, "UnitDefinitions")
        for unit in used:
            _unit_element(ud, unit)
    exp = {"startTime": "0.0", "tolerance": repr(float(options.tolerance))}
    if options.stop_time is not None:
        exp["stopTime"] = repr(float(options.stop_time))
    ET.SubElement(root, "DefaultExperiment", exp)
    derivatives, outputs = _model_variables(root, ss)
    ms = ET.SubElement(root, "ModelStructure")
    for tag, indices in (("Outputs", outputs), ("Derivatives", derivatives),
                         ("InitialUnknowns", sorted(outputs + derivatives))):
        if indices:
            group = ET.SubElement(ms, tag)
            for i in indices:
                ET.SubElement(group, "Unknown", index=str(i))
    ET.indent(root)
    return ET.tostring(root, encoding="UTF-8", xml_declaration=True)
