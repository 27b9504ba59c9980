"""Smooth replacements for kinks, for constitutive laws that sigma points cross.

The UKF and the generated Jacobians need laws that are differentiable
everywhere: a sigma point that lands on the other side of a hard kink (sign,
max, an end stop) gives a violent, non-smooth propagated map. These helpers
return sympy expressions; :func:`softplus` and :func:`sigmoid` are sympy
functions that the code generator prints as overflow-safe numpy code
(``np.logaddexp(0, z)`` and ``0.5 + 0.5*tanh(z/2)``).
"""

from __future__ import annotations

import sympy as sp


class softplus(sp.Function):
    """softplus(z) = ln(1 + e^z), smooth max(0, z); derivative sigmoid(z)."""

    nargs = 1

    def fdiff(self, argindex=1):
        return sigmoid(self.args[0])

    @classmethod
    def eval(cls, z):
        if z.is_Number and z.is_zero:
            return sp.log(2)
        return None

    def _eval_rewrite_as_exp(self, z, **kwargs):
        return sp.log(1 + sp.exp(z))

    def _eval_evalf(self, prec):
        z = self.args[0]._eval_evalf(prec)
        if z is None or not z.is_Number:
            return None
        zf = float(z)
        import math

        v = max(zf, 0.0) + math.log1p(math.exp(-abs(zf)))
        return sp.Float(v, prec)

    def _numpycode(self, printer):
        return f"{printer._module_format('numpy.logaddexp')}(0.0, {printer._print(self.args[0])})"

    def _pythoncode(self, printer):
        return self._numpycode(printer)

    def _eval_is_real(self):
        return self.args[0].is_real


class sigmoid(sp.Function):
    """sigmoid(z) = 1/(1 + e^-z) = (1 + tanh(z/2))/2."""

    nargs = 1

    def fdiff(self, argindex=1):
        s = sigmoid(self.args[0])
        return s * (1 - s)

    @classmethod
    def eval(cls, z):
        if z.is_Number and z.is_zero:
            return sp.Rational(1, 2)
        return None

    def _eval_rewrite_as_exp(self, z, **kwargs):
        return 1 / (1 + sp.exp(-z))

    def _eval_rewrite_as_tanh(self, z, **kwargs):
        return (1 + sp.tanh(z / 2)) / 2

    def _eval_evalf(self, prec):
        return self.rewrite(sp.tanh)._eval_evalf(prec)

    def _numpycode(self, printer):
        tanh = printer._module_format("numpy.tanh")
        return f"(0.5 + 0.5*{tanh}(0.5*({printer._print(self.args[0])})))"

    def _pythoncode(self, printer):
        return self._numpycode(printer)

    def _eval_is_real(self):
        return self.args[0].is_real


def smooth_sign(x, eps):
    """tanh(x/eps): sign(x) smoothed over a width ``eps`` (same unit as x)."""
    return sp.tanh(x / eps)


def smooth_abs(x, eps):
    """sqrt(x^2 + eps^2): abs(x) smoothed, >= eps."""
    return sp.sqrt(x**2 + eps**2)


def smooth_pos(x, eps):
    """eps*softplus(x/eps): max(0, x) smoothed over ``eps``."""
    return eps * softplus(x / eps)


def smooth_max(a, b, eps):
    """b + smooth_pos(a - b): max(a, b) smoothed over ``eps``."""
    return b + smooth_pos(a - b, eps)


def smooth_min(a, b, eps):
    """a - smooth_pos(a - b): min(a, b) smoothed over ``eps``."""
    return a - smooth_pos(a - b, eps)


def smooth_clip(x, lo, hi, eps):
    """x smoothly limited to [lo, hi] (one softplus on each side)."""
    return smooth_min(smooth_max(x, lo, eps), hi, eps)
