"""Declaring graphs: validation errors, the exception hierarchy, fragments,
and independence from declaration and connection order."""

import itertools

import pytest
import sympy as sp

import bondgraph as bg
from bondgraph import errors
from bondgraph.catalog.reference import dc_motor_compliant
from bondgraph.core.equations import derive


def test_exception_hierarchy():
    for cls in (errors.DanglingPortError, errors.JunctionError, errors.PortCountError,
                errors.UndeclaredSymbolError, errors.UnitMismatchError,
                errors.DuplicateNameError, errors.ConnectionError):
        assert issubclass(cls, errors.GraphError)
    for cls in (errors.CausalConflictError, errors.AlgebraicLoopError,
                errors.DerivativeCausalityError):
        assert issubclass(cls, errors.CausalityError)
    for cls in (errors.GraphError, errors.CausalityError, errors.DataError,
                errors.NumericalError, errors.CodegenError, errors.ModelError):
        assert issubclass(cls, errors.BondGraphError)


def _msd(order=0, flip=False):
    """Mass-spring-damper declared in one of several orders; ``flip`` swaps
    the arguments of every connect call."""
    g = bg.BondGraph("msd")
    m = g.param("m", 2.0, "kg")
    k = g.param("k", 50.0, "N/m")
    c = g.param("c", 1.5, "N*s/m")
    F = g.input("F", "N")
    makers = [
        lambda: g.Se("force", F),
        lambda: g.I("mass", m),
        lambda: g.C("spring", stiffness=k),
        lambda: g.R("damper", c),
    ]
    perm = list(itertools.permutations(range(4)))[order]
    els = {}
    for i in perm:
        el = makers[i]()
        els[el.name] = el
    v = g.one("v", domain="translation")
    for name in [["force", "mass", "spring", "damper"][i] for i in perm]:
        a, b = (els[name], v) if not flip else (v, els[name])
        g.connect(a, b)
    return g


@pytest.mark.parametrize("order,flip", [(0, False), (0, True), (5, False), (17, True), (23, True)])
def test_equations_independent_of_declaration_and_argument_order(order, flip):
    ref = derive(_msd(0, False))
    ss = derive(_msd(order, flip))
    assert [s.name for s in ss.states] == sorted([s.name for s in ss.states], key=[
        s.name for s in ss.states].index)
    ref_f = {s.name: f for s, f in zip(ref.states, ref.f)}
    for s, f in zip(ss.states, ss.f):
        assert sp.simplify(f - ref_f[s.name]) == 0


def test_power_direction_follows_element_convention():
    g = _msd(0, True)  # junction passed first everywhere
    for b in g.bonds:
        if b.tail.element.name == "force":
            assert b.head.element.name == "v"
        else:
            assert b.tail.element.name == "v"  # storages and R absorb power


def test_junction_to_junction_bond_direction_is_part_of_the_model():
    """Between two junctions the half-arrow follows connect(a, b): reversing
    the bond 0 -> 1(w_L) of the compliant shaft makes the shaft twist rate
    w_m + w_L instead of w_m - w_L (a different model), so the direction is
    not left to chance."""
    a = dc_motor_compliant()
    shaft_bonds = [b for b in a.bonds if {b.tail.element.name, b.head.element.name} ==
                   {"shaft", "w_L"}]
    assert len(shaft_bonds) == 1 and shaft_bonds[0].tail.element.name == "shaft"
    g = a.copy("flipped")
    bd = [b for b in g.bonds if b.name == shaft_bonds[0].name][0]
    bd.tail, bd.head = bd.head, bd.tail
    ss = derive(g)
    pm, pL = ss.state("p_J_m"), ss.state("p_J_L")
    Jm, JL = g.params["J_m"], g.params["J_L"]
    assert sp.simplify(ss.rhs("q_k_s") - (pm / Jm + pL / JL)) == 0


def test_dangling_port_names_element():
    g = bg.BondGraph("x")
    j = g.one("j")
    g.connect(g.Se("src", 1), j)
    g.connect(j, g.I("m", 1))
    g.R("loose", 1)
    with pytest.raises(errors.DanglingPortError) as e:
        g.validate()
    assert "loose" in str(e.value) and e.value.elements == ("loose",)


def test_junction_with_one_bond():
    g = bg.BondGraph("x")
    j = g.one("j")
    j2 = g.zero("lonely")
    g.connect(g.Se("src", 1), j)
    g.connect(j, g.I("m", 1))
    g.connect(j2, g.C("c", 1))
    with pytest.raises(errors.JunctionError) as e:
        g.validate()
    assert "lonely" in str(e.value) and "1 bond" in str(e.value)


def test_two_port_needs_both_ports():
    g = bg.BondGraph("x")
    j = g.one("j")
    g.connect(g.Se("src", 1), j)
    tf = g.TF("tf", 2)
    g.connect(j, tf.p1)
    with pytest.raises(errors.PortCountError) as e:
        g.validate()
    assert "tf" in str(e.value) and "p2" in str(e.value)


def test_two_port_without_explicit_port_and_reused_port():
    g = bg.BondGraph("x")
    j = g.one("j")
    tf = g.TF("tf", 2)
    with pytest.raises(errors.ConnectionError, match="tf.p1"):
        g.connect(j, tf)
    g.connect(j, tf.p1)
    with pytest.raises(errors.ConnectionError, match="already bonded"):
        g.connect(g.one("j2"), tf.p1)


def test_a_third_end_given_to_connect_is_refused_before_anything_is_bonded():
    """connect(a, r, b) read b as the bond's name: a bond named after the
    junction, b left unbonded, no error (a user chaining a -> R -> b, or a
    GY between two junctions). Now refused, naming all three, and nothing
    is bonded."""
    g = bg.BondGraph("x")
    a, b = g.one("a"), g.one("b")
    r = g.R("r", 2.0)
    with pytest.raises(errors.ConnectionError, match=r"connect\(a, r, b\): the third argument "
                                                     r"is the bond's name"):
        g.connect(a, r, b)
    assert g.bonds == [] and r.port.bond is None
    g.connect(a, r, "a to r")
    assert [bd.name for bd in g.bonds] == ["a to r"]


def test_bonding_two_absorbers_directly_is_refused():
    g = bg.BondGraph("x")
    with pytest.raises(errors.ConnectionError, match="through a 0- or 1-junction"):
        g.connect(g.I("m", 1), g.C("c", 1))


def test_varying_modulus_on_plain_tf_is_refused():
    g = bg.BondGraph("x")
    r = g.input("r")
    j1, j2 = g.one("a"), g.one("b")
    g.connect(g.Se("s", 1), j1)
    tf = g.TF("tf", r)
    g.connect(j1, tf.p1)
    g.connect(tf.p2, j2)
    g.connect(j2, g.I("m", 1))
    with pytest.raises(errors.PortCountError, match="MTF"):
        g.validate()


def test_undeclared_symbol_is_named():
    g = bg.BondGraph("x")
    ghost = sp.Symbol("ghost")
    j = g.one("j")
    g.connect(g.Se("src", 1), j)
    g.connect(j, g.R("fric", effort=lambda v: ghost * v))
    g.connect(j, g.I("m", 1))
    with pytest.raises(errors.UndeclaredSymbolError) as e:
        g.validate()
    assert "ghost" in str(e.value) and "fric" in str(e.value)


def test_duplicate_names():
    g = bg.BondGraph("x")
    g.param("a", 1)
    with pytest.raises(errors.DuplicateNameError):
        g.param("a", 2)
    g.I("m", 1)
    with pytest.raises(errors.DuplicateNameError):
        g.I("m", 2)
    # a parameter, an input and a state do not share a name: `--params F`,
    # `--fixed F=`, a record's column F would read differently
    g.input("F", "N")
    with pytest.raises(errors.DuplicateNameError, match="parameter 'F' has the name of input"):
        g.param("F", 1.0)
    with pytest.raises(errors.DuplicateNameError, match="input 'a' has the name of parameter"):
        g.input("a")
    with pytest.raises(errors.DuplicateNameError, match="state 'F' has the name of input"):
        g.state("F")


def test_bond_units_must_make_power():
    g = bg.BondGraph("x")
    j = g.one("j", effort_unit="N", flow_unit="rad/s")
    g.connect(g.Se("src", 1), j)
    g.connect(j, g.I("m", 1))
    with pytest.raises(errors.UnitMismatchError) as e:
        g.validate()
    assert "src -> j" in str(e.value) and "not a power" in str(e.value)


def test_ends_of_bond_must_agree_on_units():
    g = bg.BondGraph("x")
    a = g.one("a", domain="translation")
    b = g.zero("b", domain="rotation")
    g.connect(g.Se("src", 1), a)
    g.connect(a, b)
    g.connect(b, g.C("k", 1))
    g.connect(a, g.I("m", 1))
    with pytest.raises(errors.UnitMismatchError) as e:
        g.validate()
    assert "a -> b" in str(e.value)


def test_parameter_unit_must_fit_bond():
    g = bg.BondGraph("x")
    m = g.param("m", 1.0, "kg*m^2")  # an inertia on a translational bond
    j = g.one("j", domain="translation")
    g.connect(g.Se("src", 1), j)
    g.connect(j, g.I("mass", m))
    with pytest.raises(errors.UnitMismatchError, match="mass"):
        g.validate()
    # the right unit passes
    g2 = bg.BondGraph("y")
    m2 = g2.param("m", 1.0, "kg")
    j2 = g2.one("j", domain="translation")
    g2.connect(g2.Se("src", 1), j2)
    g2.connect(j2, g2.I("mass", m2))
    g2.validate()


def test_a_sensor_unit_must_fit_its_expression():
    """A sensor declared in N that reads a translation junction's flow
    [m/s] is refused naming the sensor (a record's column in N was bound
    to it); m/s, km/h (the same dimension) or no unit pass, and a sensor
    on a junction without a domain (units unknown) is not judged."""
    def graph(unit, domain="translation"):
        g = bg.BondGraph("s")
        j = g.one("j", domain=domain)
        g.connect(g.Se("src", g.input("F", "N")), j)
        g.connect(j, g.I("mass", g.param("m", 1.0, "kg")))
        g.sensor("v", 2 * j.f, unit=unit)
        return g

    with pytest.raises(errors.UnitMismatchError, match="sensor 'v'") as exc:
        graph("N").validate()
    assert "m/s" in exc.value.hint
    for ok in ("m/s", "km/h", None):
        graph(ok).validate()
    graph("N", domain=None).validate()


def _piston(hydraulic_on_p1: bool, modulus: str = "A"):
    """A pump-fed chamber driving a mass through a piston of area A [m^2]."""
    g = bg.BondGraph("piston")
    a = g.param("A", 2e-3, "m^2")
    ch = g.zero("chamber", domain="hydraulic")
    rod = g.one("rod", domain="translation")
    g.connect(g.Sf("pump", 1e-4), ch)
    g.connect(ch, g.C("oil", g.param("C_h", 1e-12, "m^3/Pa")))
    g.connect(rod, g.I("mass", g.param("M", 50.0, "kg")))
    tf = g.TF("piston", a if modulus == "A" else 1 / a)
    if hydraulic_on_p1:
        g.connect(ch, tf.p1)
        g.connect(tf.p2, rod)
    else:
        g.connect(rod, tf.p1)
        g.connect(tf.p2, ch)
    return g


def test_transformer_modulus_must_fit_its_bonds():
    # e1 = m e2: with the chamber on p1, Pa = m N needs m in 1/m^2, not the
    # area: the slip is named with both remedies
    with pytest.raises(errors.UnitMismatchError) as e:
        _piston(hydraulic_on_p1=True).validate()
    msg = str(e.value)
    assert "TF 'piston'" in msg and "[length] ** 2" in msg and "1 / [length] ** 2" in msg
    assert "connect p1 to 'rod' and p2 to 'chamber'" in msg and "1/(A)" in msg
    # either remedy passes: the ports swapped (F = A p, Q = A v) or 1/A
    _piston(hydraulic_on_p1=False).validate()
    _piston(hydraulic_on_p1=True, modulus="1/A").validate()


def test_gyrator_modulus_must_fit_its_bonds():
    def motor(unit):
        g = bg.BondGraph("motor")
        el = g.one("armature", domain="electrical")
        me = g.one("rotor", domain="rotation")
        g.connect(g.Se("supply", 12.0), el)
        g.connect(el, g.I("L", g.param("L", 5e-3, "H")))
        gy = g.GY("motor", g.param("k_m", 0.05, unit))
        g.connect(el, gy.p1)
        g.connect(gy.p2, me)
        g.connect(me, g.I("J", g.param("J", 1e-4, "kg*m^2")))
        return g
    motor("V*s/rad").validate()          # e1 = r f2: V = (V s/rad)(rad/s)
    motor("N*m/A").validate()            # the same dimension
    with pytest.raises(errors.UnitMismatchError) as e:
        motor("rad/(V*s)").validate()    # the inverse
    assert "GY 'motor'" in str(e.value) and "1/(k_m)" in str(e.value)
    with pytest.raises(errors.UnitMismatchError, match="GY 'motor'.*needs") as e:
        motor("m").validate()
    assert "check the modulus' parameter units" in str(e.value)


def _wheel(J_default):
    f = bg.Fragment("wheel")
    J = f.param("J", J_default, "kg*m^2", description="wheel inertia")
    b = f.param("b", 0.1, "N*m*s/rad")
    w = f.one("w", domain="rotation")
    f.connect(w, f.I("inertia", J))
    f.connect(w, f.R("bearing", b))
    f.sensor("speed", w.f, unit="rad/s")
    f.expose("hub", w)
    return f


def test_fragments_are_namespaced_and_composable():
    g = bg.BondGraph("two_wheels")
    T = g.input("T", "N*m")
    shaft = g.zero("shaft", domain="rotation")
    g.connect(g.Se("motor", T), g.one("m_j", domain="rotation"))
    g.connect("m_j", shaft)
    left = g.include(_wheel(1.0), "left")
    right = g.include(_wheel(2.0), "right")
    g.connect(shaft, left.port("hub"))
    g.connect(shaft, right.port("hub"))
    g.connect(shaft, g.C("twist", stiffness=g.param("k", 100.0, "N*m/rad")))
    assert "left.J" in g.params and "right.J" in g.params
    assert g.params["left.J"].default == 1.0 and g.params["right.J"].default == 2.0
    assert "left.inertia" in g.elements and "right.speed" in g.sensors
    ss = derive(g)
    names = [s.name for s in ss.states]
    assert "left.p_inertia" in names and "right.p_inertia" in names
    # the sensor of the right wheel reads the right wheel's momentum / J
    out = {o.name: o.expr for o in ss.outputs}
    pr = ss.state("right.p_inertia")
    assert sp.simplify(out["right.speed"] - pr / g.params["right.J"]) == 0
    with pytest.raises(errors.GraphError, match="no port 'axle'"):
        left.port("axle")


def test_fragment_symbol_passed_in_is_kept():
    g = bg.BondGraph("shared")
    mu = g.param("mu", 0.8)
    f = bg.Fragment("tyre")
    j = f.one("j", domain="translation")
    f.connect(j, f.R("slip", effort=lambda v: mu * v))
    f.connect(j, f.I("m", f.param("m", 10.0, "kg")))
    f.expose("road", j)
    h = g.include(f, "front")
    g.connect(g.Se("push", 1.0), h.port("road"))
    law = g.elements["front.slip"].law
    assert mu in law.free_symbols  # shared parameter not renamed
    g.validate()


def test_nonlinear_laws_and_sensor_on_displacement_of_a_junction():
    g = bg.BondGraph("nl")
    F = g.input("F", "N")
    Fc = g.param("Fc", 2.0, "N")
    eps = g.param("eps", 0.01, "m/s")
    k3 = g.param("k3", 5.0, "N/m^3")
    v = g.one("v", domain="translation")
    g.connect(g.Se("f", F), v)
    g.connect(v, g.I("m", 1.5))
    g.connect(v, g.R("coulomb", effort=lambda u: Fc * sp.tanh(u / eps)))
    spring = g.C("hard", effort=lambda q: k3 * q**3)
    g.connect(v, spring)
    xpos = g.displacement(v)
    g.sensor("x", xpos, unit="m")
    ss = derive(g)
    p, q = ss.state("p_m"), ss.state("q_hard")
    expect = F - Fc * sp.tanh(p / 1.5 / eps) - k3 * q**3
    assert sp.simplify(ss.rhs("p_m") - expect) == 0
    assert sp.simplify(ss.rhs("q_v") - p / 1.5) == 0
    assert sp.simplify(ss.energy - (p**2 / 3 + k3 * q**4 / 4)) == 0


@pytest.mark.parametrize("written, remedy", [
    ("rotational", "domain='rotation'"),
    ("Electric", "domain='electrical'"),
    ("translational", "domain='translation'"),
    ("mechanical", "domain='translation' (a linear motion) or domain='rotation' (a shaft)"),
])
def test_a_misspelt_domain_names_the_one_meant(written, remedy):
    from bondgraph.errors import ElementError

    g = bg.BondGraph("misspelt")
    with pytest.raises(ElementError, match="unknown domain") as err:
        g.one("shaft", domain=written)
    assert err.value.hint == remedy
    assert list(err.value.elements) == ["shaft"]


def test_an_unknown_domain_without_a_near_name_gets_the_list_only():
    from bondgraph.errors import ElementError

    with pytest.raises(ElementError, match="known: translation, rotation") as err:
        bg.BondGraph("odd").zero("j", domain="xyz")
    assert err.value.hint is None


@pytest.mark.parametrize("kind, written, meant", [
    ("C", "spring", "stiffness"), ("TF", "ratio", "modulus"), ("GY", "gain", "modulus"),
])
def test_an_argument_of_another_tool_names_the_element_and_the_one_meant(kind, written, meant):
    """C(spring=...) raised Python's bare TypeError from the base class;
    the error now names the element, what its class takes and the remedy."""
    from bondgraph.errors import ElementError

    g = bg.BondGraph("words")
    said = f"{kind} 'x': unknown argument\\(s\\) {written};"
    with pytest.raises(ElementError, match=said) as err:
        if kind == "C":
            g.C("x", **{written: 1.0})
        else:
            getattr(g, kind)("x", 2.0, **{written: 1.0})
    assert meant in str(err.value).split("takes")[1]
    assert err.value.hint == f"{meant}= in place of {written}="
    assert list(err.value.elements) == ["x"]
    with pytest.raises(ElementError, match="unknown argument\\(s\\) colour; R takes") as err:
        g.R("y", 1.0, colour="red")
    assert err.value.hint is None


@pytest.mark.parametrize("kind, written, meant", [
    ("C", "capacitance", "compliance"), ("C", "capacity", "compliance"),
    ("I", "inductance", "inertance"), ("I", "mass", "inertance"), ("I", "inertia", "inertance"),
    ("R", "damping", "resistance"),
])
def test_a_name_of_the_same_parameter_is_taken_as_it(kind, written, meant):
    """C(capacitance=2e-6) is C(compliance=2e-6): the same law and energy
    (e = q/C, q²/2C); given under both names it is refused, named."""
    from bondgraph.errors import ElementError

    g = bg.BondGraph("words")
    a = getattr(g, kind)("a", **{written: 2e-6})
    b = getattr(g, kind)("b", **{meant: 2e-6})
    assert getattr(a, meant) == getattr(b, meant) == sp.Float(2e-6)
    if kind != "R":
        va, vb = a.state, b.state
        assert sp.simplify(a.law.subs(va, 1) - b.law.subs(vb, 1)) == 0
        assert sp.simplify(a.energy.subs(va, 3) - b.energy.subs(vb, 3)) == 0
        assert float(a.law.subs(va, 1)) == pytest.approx(5e5)
    with pytest.raises(ElementError, match=f"{kind} 'c': {meant} given twice") as err:
        getattr(g, kind)("c", 1.0, **{written: 2.0})
    assert list(err.value.elements) == ["c"]
