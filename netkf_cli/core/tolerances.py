"""Every numerical tolerance of netkf, in one place (core layer: imports nothing of netkf).

Each constant says what it decides and why its value; modules import them from here instead of
writing their own ``1e-9``.
"""

from __future__ import annotations

import sys

PSD_TOL = 1e-9
"""Relative tolerance of the PSD order: X ≤ M iff min eig(M − X) ≥ −PSD_TOL·max(1, ‖M‖).
Riccati iterates converge to ~1e-12 relative; 1e-9 absorbs that without merging distinct jump points."""

EXACT_PSD_TOL = 1e-10
"""The PSD order inside the exact stationary enumeration of the smoother's Pr[P ≤ M] (Leong et al. 2008,
analysis/smoothing.exact_probability): a node counts as ≤ M (its weight added to the certified lower bound) only
when min eig ≥ −EXACT_PSD_TOL·‖·‖. Tighter than PSD_TOL: a looser tolerance could count a node slightly above M
into the lower bound, a tighter one only leaves such a node undecided (refined, or its weight left in the
reported gap), so the bracket stays certified."""

SYM_TOL = 1e-9
"""Relative asymmetry ‖X − Xᵀ‖ / max(1, ‖X‖) above which an input matrix is refused as not symmetric."""

PSD_INPUT_TOL = 1e-10
"""Relative tolerance of min eig(Q) ≥ −tol·max(1, ‖Q‖) for user input Q (and P0): round-off of a
hand-typed PSD matrix passes, a genuinely indefinite one does not."""

RESCUE_RATIO = 1e8
"""The information-form rescue (kalman.Rescue): a run whose prior covariance has
tr P⁻ > RESCUE_RATIO · scale is updated in information form (P⁻⁻¹ + CᵀR⁻¹C)⁻¹. The standard form
P − P Cᵀ S⁻¹ C P cancels every digit once ‖P‖/‖R‖ ≳ 1/ε ≈ 4.5e15; 1e8 leaves a margin of 1e7 and
is far above any covariance a stable or moderately unstable filter reaches. That holds for one row at a time (S a
number: the error is ε·‖P‖/‖P⁺‖); with several rows at once it grows like ‖P‖², and kalman.burst_limit lowers the
limit per system to where the error is still ε·RESCUE_RATIO."""

HEAVY_TAIL_RSE = 0.5
"""A Monte Carlo mean is flagged heavy-tailed when the relative standard error of its sample
variance, √((m₄ − s⁴)/n)/s², exceeds this (the standard error itself is then uncertain by more than
about 25 %), or when any run is non-finite. Light tails pass at modest n (exponential data: 0.28 at
n = 200); an infinite fourth moment never does."""

RARE_EVENT_FRACTION = 0.5
"""A mean is flagged rare-event dominated when more than this fraction of its sum comes from the
single largest run (with n ≥ 2): the estimate then rests on one event of probability ~1/n."""

SOLVER_TOL = 1e-8
"""Feasibility and duality-gap tolerance of the critical-rate SDPs (:mod:`netkf_cli.linalg.sdp`; Clarabel's defaults). A
margin t* below it is solver noise: the certificate check (:data:`CRITICAL_MARGIN_TOL`) then decides."""

DARE_RTOL = 1e-12
"""Relative convergence tolerance of fixed-point Riccati iterations (P*, P̄, steady states)."""

ZERO_INNOVATION_RTOL = 1e-9
"""(appended, the Markov-mode filters) An innovation direction whose variance is ≤ this times
tr Σ + tr P⁻ counts as zero and gets no gain (kalman.update_pinv): a held packet, whose value the
receiver already knows, has variance 0 up to round-off (≈1e-16 relative); 1e-9 separates it from
any genuinely informative measurement."""

FIXED_GAIN_PRECISION = 1e-6
"""(appended, the Markov-mode filters) A fixed-gain filter's per-run error covariance C M Cᵀ read off the
joint second moment M of [plant state; filter state] is reported as ``inf`` (lost, counted as diverged)
when its round-off bound ε_mach·‖C‖_F²·tr M exceeds this fraction of tr(C M Cᵀ): for an unstable plant
(A = diag(1e6, 0.5)) M grows without bound and the subtraction cancels every digit — a wrong finite
number must not be reported. 1e-6 keeps six correct digits; stable plants are ~1e-15 from it."""

GOLDEN_CLOSED_RTOL = 1e-7
"""Golden comparison of a closed-form column: relative tolerance (the committed CSVs keep 10 significant digits)."""

GOLDEN_CLOSED_ATOL = 1e-9
"""Golden comparison of a closed-form column: absolute tolerance, times the column's scale."""

MC_SIGMAS = 5.0
"""A Monte Carlo number agrees with another (a golden column, a printed number under `--check`) within this many
combined standard errors."""

STOCHASTIC_ROW_TOL = 1e-9
"""A transition matrix row sums to 1 within this (and no entry is below −this)."""

SMOOTHING_EXACT_TOL = 1e-13
"""Per-node weight tolerance of the smoothing reference enumerations (the certified brackets are < 1e-11 wide)."""

SMOOTHING_MEAN_TOL = 1e-10
"""Per-node trace tolerance of the exact stationary means (analysis/smoothing)."""

CRITICAL_RHO_TOL = 1e-9
"""Critical arrival rate: |σ| within this of 1 counts as "on the unit circle"."""

CRITICAL_MARGIN_TOL = 1e-9
"""Critical arrival rate: an LMI solution certifies feasibility when the smallest eigenvalue of the (numerically
re-evaluated) block matrix and of Y exceeds this (both are normalised by Y ≤ I)."""

CRITICAL_BISECTION_TOL = 1e-5
"""Critical arrival rate: default width of the bisection bracket on λ (``analysis.bisection_tol``)."""

CRITICAL_BISECTION_TOL_MIN, CRITICAL_BISECTION_TOL_MAX = 1e-9, 0.1
"""The range of that width accepted by a scenario (``analysis.bisection_tol``) and by ``netkf critical --tol`` alike:
a bracket wider than 0.1 says little about λ_max; below 1e-9 the bisection only chases the LMI solver's rounding."""

CRITICAL_RANK_TOL = 1e-8
"""C restricted to a quasi-equiblock counts as injective when σ_min(C V) > CRITICAL_RANK_TOL·‖C‖ (V orthonormal): scale-free."""

DELAY_EXACT_TOL = 1e-6
"""Default tolerance of the exact delay-buffer probabilities (analysis/delay_exact): the enumeration stops when the
unexplored probability mass is below it."""

LAMBDA_MAX_MARGIN = 1e-11
"""Relative margin of the compiled reductions' certified decisions λ_max(P) ≤ th, times |th| + max_i Σ_j |P_ij|
(≥ ‖P‖₂): see :mod:`netkf_cli.linalg._reduce_numba`."""

EIGEN_GAP_SE = 5.0
"""‖E P‖ (metrics/norm_of_mean): λ₁ − λ_i of the mean must exceed this many standard errors s_i of the (u, u_i) block
for the delta-method s.e. (else flag_reason eigen_gap)."""

ROUNDOFF_VARIANCE = 100.0 * sys.float_info.epsilon
"""‖E P‖: a per-run variance below ROUNDOFF_VARIANCE · ‖M̂‖² is rounding (every run the same number, e.g. scenario 2
with an invertible C, exact per run): the s.e. is 0, as :func:`netkf_cli.core.stats.mean_se` rules for a scalar mean."""
