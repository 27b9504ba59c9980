"""Branch-free vector maths of the numba column kernels, as plain Python.

sin, cos, atan, exp and tanh by range reduction and rational or polynomial
approximations after S. L. Moshier, *Methods and Programs for Mathematical
Functions* (1989; the Cephes library), with selects (:func:`_sel`) instead of
branches, so that LLVM vectorises a loop that computes them (numba's pip
LLVM has no vector libm; a libm call keeps a loop scalar). Within 2 ulp of
numpy (tests/test_vmath.py: 1e6 points per range, the non-finite values);
sin and cos for |x| < 1e8 (the column kernels count larger arguments and
recompute with numpy's functions).

These are real functions: importable and callable as plain Python on
finite floats and numpy scalars (:func:`_sel` below is ``a if c else b``;
NaN or an infinite argument can fail there in ``np.int64``, where the
compiled select has computed both branches). They are also the source of
generated code (:mod:`bondgraph.core.codegen_numba`):

* the functions of :data:`INLINE` are compiled once per installation by
  :mod:`bondgraph.numerics.vmath_jit` (their code objects, with ``_sel``
  numba's ``@intrinsic`` select: one LLVM select instruction) and called by
  the column kernels, which LLVM inlines them into; ``vmath_inline`` reads
  their syntax tree (``inspect.getsource``, ``ast``) and expands them, and
  the calls between them, into straight code (what the column kernels ran
  up to ``NUMBA_CODEGEN_VERSION`` 7; the tests compare the two). A change of
  their code changes every compiled column kernel (numba's cache of a kernel
  does not see it): ``NUMBA_CODEGEN_VERSION`` + 1.
* :func:`_tanh` (the scalar tanh of the point kernels) is emitted verbatim,
  source text and docstring included, under an ``@njit`` decorator
  (``NUMBA_TANH``): any edit of its text, a comment too, changes the
  generated modules.

A change of the generated text needs ``NUMBA_CODEGEN_VERSION`` + 1 and
``bondgraph generate`` (``bondgraph generate --check`` fails until then).
"""

from __future__ import annotations

import numpy as np

#: the branch-free functions that the column kernels expand inline (by name)
INLINE = ("_vatan", "_vsincos", "_vsin", "_vcos", "_pow2", "_vexp", "_vtanh")


def _sel(c, a, b):
    """``a if c else b`` for plain Python. The generated modules define
    ``_sel`` as numba's ``@intrinsic`` select instead (both ``a`` and ``b``
    computed, no branch: ``bondgraph.core.codegen_numba.NUMBA_SELECT``)."""
    return a if c else b


# tanh of the numba modules: for |x| >= 0.55, 1 - 2/(exp(2|x|) + 1) with the sign
# of x (glibc's tanh takes expm1 there, 2.5x the time of exp: tanh was a
# sixth of the fused UKF kernel's time on vehicle_full, perf); np.tanh below.
# Within 4.3e-16 relative of np.tanh (1e6 points on [-30, 30]); ±1 at ±inf
# and for large |x|, NaN for NaN (the comparison is false, exp(NaN) is NaN).
# Emitted verbatim into the generated numba modules (NUMBA_TANH): its text,
# the docstring with its historical name of the template too, is part of
# the generated code; edit it only with NUMBA_CODEGEN_VERSION + 1.
def _tanh(x):
    """tanh(x) by exp for |x| >= 0.55 (bondgraph.core.codegen.NUMBA_TANH)."""
    a = abs(x)
    if a < 0.55:
        return np.tanh(x)
    r = 1.0 - 2.0 / (np.exp(2.0 * a) + 1.0)
    return r if x > 0 else -r


def _vatan(x):
    """atan(x): 3 ranges by selects, a 4/5 rational in x² (Moshier 1989)."""
    a = abs(x)
    big = a > 2.41421356237309504880
    mid = a > 0.66
    z0 = _sel(big, -1.0, _sel(mid, a - 1.0, a)) / _sel(big, a, _sel(mid, a + 1.0, 1.0))
    y0 = _sel(big, 1.5707963267948966, _sel(mid, 0.7853981633974483, 0.0))
    mb = _sel(big, 6.123233995736765886130e-17, _sel(mid, 3.061616997868382943065e-17, 0.0))
    z = z0 * z0
    p = ((((-8.750608600031904122785e-1 * z - 1.615753718733365076637e1) * z
           - 7.500855792314704667340e1) * z - 1.228866684490136173410e2) * z
         - 6.485021904942025371773e1)
    q = (((((z + 2.485846490142306297962e1) * z + 1.650270098316988542046e2) * z
           + 4.328810604912902668951e2) * z + 4.853903996359136964868e2) * z
         + 1.945506571482613964425e2)
    r = y0 + ((z0 * (z * p / q) + z0) + mb)
    return _sel(x < 0, -r, r)


def _vsincos(a, shift):
    """sin (shift 0) or cos (shift 2) of a >= 0 below 1e8: reduction by π/4 in
    three parts, degree-6 polynomials in z² (Moshier 1989)."""
    y0 = np.floor(a * 1.2732395447351628)
    j0 = _sel(a < 1e15, np.int64(y0), np.int64(0))
    odd = (j0 & 1) == 1
    j1 = _sel(odd, j0 + 1, j0)
    y = _sel(odd, y0 + 1.0, y0)
    j2 = (j1 + shift) & 7
    neg = j2 > 3
    j = _sel(neg, j2 - 4, j2)
    z = (((a - y * 7.85398125648498535156e-1) - y * 3.77489470793079817668e-8)
         - y * 2.69515142907905952645e-15)
    zz = z * z
    c = 1.0 - 0.5 * zz + zz * zz * ((((((-1.13585365213876817300e-11 * zz
                                         + 2.08757008419747316778e-9) * zz
                                        - 2.75573141792967388112e-7) * zz
                                       + 2.48015872888517045348e-5) * zz
                                      - 1.38888888888730564116e-3) * zz
                                     + 4.16666666666665929218e-2))
    s = z + z * zz * ((((((1.58962301576546568060e-10 * zz - 2.50507477628578072866e-8) * zz
                          + 2.75573136213857245213e-6) * zz - 1.98412698295895385996e-4) * zz
                        + 8.33333333332211858878e-3) * zz - 1.66666666666666307295e-1))
    r = _sel((j == 1) | (j == 2), c, s)
    return _sel(neg, -r, r)


def _vsin(x):
    """sin(x) for |x| < 1e8 (_vsincos)."""
    r = _vsincos(abs(x), 0)
    return _sel(x < 0, -r, r)


def _vcos(x):
    """cos(x) for |x| < 1e8 (_vsincos)."""
    return _vsincos(abs(x), 2)


def _pow2(n):
    """2**n for |n| <= 1022 from the bits of |n| (selects and exact products)."""
    neg = n < 0
    a = _sel(neg, -n, n)
    p0 = _sel((a & 1) != 0, _sel(neg, 0.5, 2.0), 1.0)
    p1 = p0 * _sel((a & 2) != 0, _sel(neg, 0.25, 4.0), 1.0)
    p2 = p1 * _sel((a & 4) != 0, _sel(neg, 0.0625, 16.0), 1.0)
    p3 = p2 * _sel((a & 8) != 0, _sel(neg, 0.00390625, 256.0), 1.0)
    p4 = p3 * _sel((a & 16) != 0, _sel(neg, 1.52587890625e-05, 65536.0), 1.0)
    p5 = p4 * _sel((a & 32) != 0, _sel(neg, 2.3283064365386963e-10, 4294967296.0), 1.0)
    p6 = p5 * _sel((a & 64) != 0, _sel(neg, 5.421010862427522e-20, 1.8446744073709552e19), 1.0)
    p7 = p6 * _sel((a & 128) != 0, _sel(neg, 2.938735877055719e-39, 3.402823669209385e38), 1.0)
    p8 = p7 * _sel((a & 256) != 0, _sel(neg, 8.636168555094445e-78, 1.157920892373162e77), 1.0)
    return p8 * _sel((a & 512) != 0, _sel(neg, 7.458340731200207e-155, 1.3407807929942597e154),
                     1.0)


def _vexp(x):
    """exp(x) = 2**n exp(r), |r| <= ln2/2, a 2/3 rational in r² (Moshier 1989);
    inf above 709.78, 0 below -708.40 (numpy: a subnormal there), NaN for NaN."""
    xc = _sel(x > 709.79, 709.79, _sel(x < -708.4, -708.4, x))
    fl = np.floor(1.4426950408889634 * xc + 0.5)
    r = (xc - fl * 6.93145751953125e-1) - fl * 1.42860682030941723212e-6
    n = np.int64(fl)
    xx = r * r
    px = r * ((1.26177193074810590878e-4 * xx + 3.02994407707441961300e-2) * xx
              + 9.99999999999999999910e-1)
    e0 = 1.0 + 2.0 * (px / ((((3.00198505138664455042e-6 * xx + 2.52448340349684104192e-3) * xx
                              + 2.27265548208155028766e-1) * xx + 2.00000000000000000009e0)
                            - px))
    big = n > 1000
    e1 = _sel(big, e0 * 2.0, e0) * _pow2(_sel(big, n - 1, n))
    e = _sel(x > 7.09782712893383996843e2, np.inf, _sel(x < -7.08396418532264106224e2, 0.0, e1))
    return _sel(x != x, x, e)


def _vtanh(x):
    """tanh(x): x + x³ P(x²)/Q(x²) below |x| = 0.625 (Moshier 1989), else
    1 − 2/(exp(2|x|) + 1) with the sign of x, exp(2|x|) = 2**n (q + p)/(q − p)
    as in _vexp; one division for both branches (a select of numerator and
    denominator); NaN for NaN."""
    a = abs(x)
    z = x * x
    aa = 2.0 * _sel(a > 40.0, 40.0, a)
    fl = np.floor(1.4426950408889634 * aa + 0.5)
    r = (aa - fl * 6.93145751953125e-1) - fl * 1.42860682030941723212e-6
    rr = r * r
    p = r * ((1.26177193074810590878e-4 * rr + 3.02994407707441961300e-2) * rr
             + 9.99999999999999999910e-1)
    q = (((3.00198505138664455042e-6 * rr + 2.52448340349684104192e-3) * rr
          + 2.27265548208155028766e-1) * rr + 2.00000000000000000009e0)
    d = q - p
    small = a < 0.625
    num = _sel(small, x * z * ((-9.64399179425052238628e-1 * z - 9.92877231001918586564e1) * z
                               - 1.61468768441708447952e3), 2.0 * d)
    den = _sel(small, ((z + 1.12811678491632931402e2) * z + 2.23548839060100448583e3) * z
               + 4.84406305325125486048e3, _pow2(np.int64(fl)) * (q + p) + d)
    t = num / den
    big = 1.0 - t
    return _sel(small, x + t, _sel(x < 0, -big, big))
