"""Closing the loop with measured data: trace the residual to an effect the
model lacks, add it to the graph, re-estimate, report the error before and
after.

One step of the loop:

1. **Fit** the current model: maximum-likelihood estimate of the chosen
   parameters with the batched UKF (:mod:`bondgraph.inference.estimate`), warm-started.
2. **Residuals**: UKF innovations and free-run simulation errors per output;
   whiteness, NIS, bias, spectral peaks, operating regions
   (:mod:`bondgraph.diagnose.residuals`).
3. **Evidence** for every candidate of the effect library
   (:mod:`bondgraph.diagnose.effects`) at every place the graph offers:

   * additive effects (friction laws, drags, offsets, gains, sensor
     offset/gain/rectification) are all added at once to a *probe* model at
     their neutral value β = 0. One batched UKF run with each β nudged gives
     the innovation signatures J = ∂ε/∂β; with whitened innovations e and
     signatures G the score (Lagrange-multiplier) statistic of a candidate
     with columns c is LM = bᵀ A⁻¹ b, b = Σ G_cᵀ e, A = Σ G_cᵀ G_c: how much
     of the innovation energy the candidate's signature explains. Under "the
     effect is absent" LM ~ χ²(k) (Rao 1948; Engle 1984).
   * structural effects (slip, compliance, low-pass, saturation, dead zone,
     end stops, backlash, disturbance) have no neutral value; each is built
     and fitted over a grid of its parameter in one batched UKF run, giving
     the likelihood-ratio statistic LR = 2 (NLL₀ − NLL₁) ~ χ²(k).

   Both statistics are χ²(k): candidates are ranked by the predicted
   decrease of AIC, statistic − 2k, which is comparable between them.
4. **Confirm** the best few by building the real augmented graph and fitting
   its new parameters (likelihood ratio), then **accept** the best one only
   if, after re-estimating all parameters warm-started, the information
   criterion (AIC by default, or BIC) and the residual whiteness (sum of the
   Ljung-Box statistics) both improve.
5. Repeat until no candidate is significant (Bonferroni-corrected p-value
   above ``significance``) or nothing is accepted.

The user's graph is never modified: every step works on a copy, and the
final augmented graph is written out as a new declared model
(``augmented_model.py``, which rebuilds it from the user's builder plus the
named effects), with its generated code and the estimates. The loop hands its
partial :class:`~bondgraph.diagnose.result.LoopResult` to ``on_update`` after
the initial fit and after every step; the report writer
(:class:`bondgraph.report.loop_report.LoopReporter`) rewrites ``report.json``,
``report.md`` and the PNG plots from it, so an interrupted run keeps its work.

Where each part lives
---------------------
* :mod:`~bondgraph.diagnose.settings` -- :class:`LoopSettings` and its groups
  (:class:`AcceptRule`, :class:`SearchOptions`, :class:`FreeRunOptions`).
* :mod:`~bondgraph.diagnose.runner` -- :func:`run_loop`, the orchestration and its log;
  :func:`chosen_numerics`, the filter's numerics chosen for a user's record
  as the command line chooses them.
* :mod:`~bondgraph.diagnose.fit` -- the fit of one model (step 1), the UKF prior.
* :mod:`~bondgraph.diagnose.metric` -- the error reported before and after.
* :mod:`~bondgraph.diagnose.residuals` -- step 2.
* :mod:`~bondgraph.diagnose.scoring` -- step 3 (score test, line probe,
  likelihood-ratio grids).
* :mod:`~bondgraph.diagnose.confirm`, :mod:`~bondgraph.diagnose.accept` -- step 4.
* :mod:`~bondgraph.diagnose.result` -- :class:`LoopResult` and its records.
* :mod:`~bondgraph.diagnose.inference_calls` -- every call into
  :mod:`bondgraph.inference`.

References
----------
Rao, C. R. (1948). Large sample tests of statistical hypotheses concerning
several parameters. Proc. Cambridge Phil. Soc. 44, 50-57. Engle, R. F. (1984).
Wald, likelihood ratio and Lagrange multiplier tests in econometrics.
Handbook of Econometrics II, ch. 13. Akaike, H. (1974). A new look at the
statistical model identification. IEEE TAC 19(6), 716-723. Ljung & Box
(1978), see :mod:`bondgraph.diagnose.residuals`.
"""

from bondgraph.diagnose.result import Candidate, LoopResult, Step
from bondgraph.diagnose.runner import chosen_numerics, run_loop
from bondgraph.diagnose.settings import AcceptRule, FreeRunOptions, LoopSettings, SearchOptions

__all__ = ["AcceptRule", "Candidate", "FreeRunOptions", "LoopResult", "LoopSettings",
           "SearchOptions", "Step", "chosen_numerics", "run_loop"]
