"""The report's paragraph on parameters the final fit does not identify
apart (report.loop_report.flat_text): a flat direction (relative eigenvalue
of the Fisher information below 1e-4 at a unit diagonal) whose parameters
this record still determines to within 1 % reads as a narrow ridge, not as
"one point of a ridge". The numbers are a pump-fed piston's final fit
(1 kHz, 20 001 samples; Cramér-Rao and robust std as its report gave them)."""

from types import SimpleNamespace

from bondgraph.report.loop_report import NARROW_RIDGE_REL, flat_text

EST = {"C_h": 6.80591e-13, "R_l": 9.99748e10, "M": 51.4393, "k": 200423.0, "c": 2292.58,
       "coulomb.rod.Fc": 279.588}
STD = {"C_h": 3.72e-17, "R_l": 5.86e6, "M": 0.0117, "k": 12.3, "c": 0.813,
       "coulomb.rod.Fc": 0.0333}
ROBUST = {"C_h": 4.09e-17, "R_l": 3.8e6, "M": 0.0133, "k": 10.8, "c": 0.624,
          "coulomb.rod.Fc": 0.0217}
FLAT = ("M", "c", "noise.x", "coulomb.rod.Fc", "k", "noise.p", "R_l", "C_h")


def final(std=STD, flat=FLAT):
    return SimpleNamespace(flat=flat, ridge="", estimates=EST, std=std)


def test_a_narrow_ridge_is_said_to_be_determined_by_this_record():
    text = flat_text(final(), ROBUST)
    # the loosest: c, its Cramér-Rao std 0.813 of 2292.58 (the robust 0.624 is smaller)
    assert f"{0.813 / 2292.58:.2%}" == "0.04%"
    assert "determines each to within 0.04% of its value" in text
    assert "nearly collinear" in text and "one point of a ridge" not in text


def test_a_loose_or_undetermined_parameter_keeps_the_ridge_warning():
    loose = dict(STD, M=0.02 * EST["M"])          # 2 % > NARROW_RIDGE_REL
    assert 0.02 > NARROW_RIDGE_REL
    for std in (loose, dict(STD, M=None)):        # None: on a bound, no std
        text = flat_text(final(std), ROBUST)
        assert text.startswith("The record does not identify M, c, noise.x") and \
            "one point of a ridge" in text
    assert flat_text(final(flat=()), ROBUST) == ""
    # a flat parameter without an estimate, or a scale combination found
    # along the direction: the warning stands
    assert "one point of a ridge" in flat_text(final(flat=("M", "ks")), ROBUST)
    scaled = SimpleNamespace(flat=FLAT, ridge="; as relative changes: M +1.00, k +1.00",
                             estimates=EST, std=STD)
    assert "one point of a ridge" in flat_text(scaled, ROBUST)
