"""Where does the base model miss? Mismatch maps and classic residual tests.

Everything is computed in the whitened space of :mod:`fricjax.diagnose.whiten`, where under
H0 (the base model is right, the residual is preprocessed displacement noise) the whitened
residual ``r_w = W·r`` [M] is N(0, σ_x²·I) up to the base fit. Notation:

* ``Q`` [M, p]: orthonormal basis of the nuisance directions, the whitened base Jacobian
  ``J_w = W·∂r/∂θ`` (a fitted θ has used them) plus the whitener's excluded samples;
  ``P⊥ = I − Q Qᵀ``; ``dof = M − p``; ``σ̂_x² = ‖P⊥ r_w‖² / dof``.
* Score statistic of a regressor set ``G`` [n, k] (a force shape, N per unit amplitude):
  ``G_w = W·G``, ``G⊥ = P⊥ G_w``,

      S = r_wᵀ G⊥ (G⊥ᵀ G⊥)⁻¹ G⊥ᵀ r_w / σ̂²,

  the Lagrange-multiplier test of adding ``G·β`` to the model. With σ̂ from the same
  residual, ``S/dof ~ Beta(k/2, (dof − k)/2)`` exactly under H0 (large dof: ``S ~ χ²_k``);
  that gives each bin's p-value.
* A map is a family of B regressor sets (one per bin); its family statistic is the maximum
  score over the bins, calibrated by Monte Carlo: ``z ~ N(0, I_M)`` (matrix products, no
  loop over draws), projected off Q, normalised by its own σ̂². The family-wise p-value is
  ``(1 + #{null max ≥ observed max}) / (1 + n_mc)``. Significant bins are chosen step-down:
  the best bin is significant when its score exceeds the ``1 − α`` quantile of its map's
  null maximum (so a map raises a false alarm with probability α on a null record); it then
  joins the nuisance and the next best bin is scored conditionally, against the same
  threshold, until none passes. (Marginally, a strong local effect also lights up the bins
  whose whitened regressors correlate with it.)

Maps (``MapBin.variable``):

* ``time``: n_bins equal intervals; regressor ``1_B`` (k = 1): a force localised in time
  (impact, drift). No ``1_B·sgn v`` column: sgn of the measured v flips at reversals in step
  with the noise (errors in variables) and biased the map on null records.
* ``velocity+`` / ``velocity-``: quantile bins of v over v > 0 and v < 0 separately;
  regressor ``1_B`` (direction already fixes the sign of any friction-like deficit).
* ``position``: quantile bins of x; ``[1_B, 1_B·sgn v]`` (position-dependent force or
  friction: cogging, a burr, a seal).
* ``acceleration``: quantile bins of a; ``1_B`` (inertial mismatch).
* ``frequency``: every kept bin; regressors the whitened unit vectors of its cosine and sine
  coefficients (k = 2, k = 1 at DC/Nyquist), i.e. the periodogram of the projected, whitened
  residual, each bin χ²₂-like, max-calibrated over frequencies like the other maps.

Quantile bins hold ≥ 5 samples each (fewer bins when a map has fewer than 5·n_bins samples).
Classic tests: Ljung–Box on the whitened residual read as a time series (see
:func:`baseband`) and score tests of the residual against v, x, a, |v| and sgn v.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jaxtyping import Array, Float
from scipy import stats

from fricjax.data.preprocess import derivatives, noise_gains
from fricjax.diagnose.evidence import near_rest_band, record_noise
from fricjax.diagnose.whiten import (
    Whitener,
    linear_damping,
    make_whitener,
    noise_spectrum,
)
from fricjax.errors import FricjaxError, where
from fricjax.problem import Problem, needs_input
from fricjax.search.fast_compile import FAST_COMPILE

VARIABLES: tuple[str, ...] = (
    "time",
    "velocity+",
    "velocity-",
    "position",
    "acceleration",
    "frequency",
)
CROSS: tuple[str, ...] = ("v", "x", "a", "|v|", "sgn v")
# Relative size below which a (whitened) column counts as lying in the nuisance span.
_RANK_TOL = 1e-9
# Fewest samples in a quantile bin.
_MIN_PER_BIN = 5
# Monte Carlo draws per block (bounds memory at M × _MC_BLOCK floats per matrix).
_MC_BLOCK = 500


class MapBin(NamedTuple):
    """One bin of a mismatch map.

    ``variable`` (one of :data:`VARIABLES`); ``lo``, ``hi``: bin edges in the variable's unit
    (s, m/s, m, m/s², Hz); ``mean_residual``: mean residual over the bin's samples [N] (for
    ``frequency``: amplitude ``2|R_k|/n`` of the residual at the bin [N]); ``score``: the
    score statistic; ``p_value``: its single-bin p-value (both marginal); ``significant``:
    chosen by the step-down procedure (module docstring) at family-wise level α.
    """

    variable: str
    lo: float
    hi: float
    mean_residual: float
    score: float
    p_value: float
    significant: bool


class LocateReport(NamedTuple):
    """Result of :func:`locate`.

    ``bins``: every bin of every map (order of :data:`VARIABLES`); ``significant``: the
    significant ones, smallest p-value first; ``ljung_box_p``/``ljung_box_stat``: whiteness
    of the whitened residual; ``crosscorr``: p-values of the score tests against v, x, a,
    |v|, sgn v (1.0 when the regressor lies in the base model's span, NaN when its own
    measurement noise makes it untestable, see :class:`CrossTest`); ``sigma``: σ̂_x [m];
    ``family_p``: family-wise p-value of each map (max score, Monte Carlo calibrated).
    """

    bins: list[MapBin]
    significant: list[MapBin]
    ljung_box_p: float
    ljung_box_stat: float
    crosscorr: dict[str, float]
    sigma: float
    family_p: dict[str, float]


class Family(NamedTuple):
    """A map's regressors, ready to score: B bins, each an orthonormal basis of its
    whitened, projected regressors.

    Dense form: ``basis`` [B, M, k] (zero columns beyond a bin's rank). Unit-vector form
    (frequency map): ``rows`` [B, k] indices into the whitened vector and ``inv_sqrt``
    [B, k, k] = ``(E_bᵀ P⊥ E_b)^(+1/2)``, so the score is ``‖inv_sqrt·(P⊥ z)[rows]‖²``.
    ``rank`` [B]; ``lo``, ``hi`` [B] bin edges; ``members`` [B, n] bool sample masks (dense
    form) or None.
    """

    variable: str
    lo: np.ndarray
    hi: np.ndarray
    rank: np.ndarray
    basis: np.ndarray | None
    rows: np.ndarray | None
    inv_sqrt: np.ndarray | None
    members: np.ndarray | None


class LocatePlan(NamedTuple):
    """Everything about a located problem that does not depend on the residual: whitener,
    nuisance basis, map families, cross-correlation directions and Monte Carlo nulls."""

    whitener: Whitener
    Q: np.ndarray
    dof: int
    families: list[Family]
    null_max: dict[str, np.ndarray]
    cross: dict[str, CrossTest | None]
    lags: int
    lb_null: np.ndarray


class CrossTest(NamedTuple):
    """Score test of the residual against one measured signal g (v, x, a, |v| or sgn v).

    g is measured with the same noise that makes the residual (errors in variables): its
    whitened noise part ``w = W·D_g e`` correlates with ``u = W·K e``. Under H0, with
    ``gp = P⊥ W g`` and ``T = gpᵀ P⊥ r_w``: ``E T = σ²·bias`` and ``Var T = σ²·‖P⊥ W g_true‖²
    + σ⁴·var_q``, where ``bias = E[(P⊥w)ᵀ(P⊥u)]``, ``var_q`` its variance and
    ``noise = E‖P⊥w‖²`` (so ``‖P⊥ W g_true‖² ≈ ‖gp‖² − σ²·noise``) come from unit-variance
    draws of e passed through :func:`~fricjax.data.preprocess.derivatives` (D_g: x -> v, a,
    sgn(v)·v, identity for x). For the acceleration of the paper twin the correction is
    essential: its whitened noise part outweighs its signal (2.7e-6 vs 7.3e-6 m off the base
    span on a 1 s record at σ_x = 24 µm) and the uncorrected statistic sits 11.6 σ off zero.
    When the noise part exceeds 10 % of ‖gp‖² the test is reported untestable (NaN).
    sgn v has no linear noise part but flips where |v| is within the noise: ``flip_speed``
    is ``min |v|/(σ_v/σ_x)`` over the samples the whitener keeps [1/s·m/s]; the test is
    NaN when that is below 4·σ̂_x (inf for the other signals).
    """

    gp: np.ndarray
    bias: float
    var_q: float
    noise: float
    flip_speed: float


# -- linear algebra shared with the selection code -------------------------------------------


def orthonormal_basis(
    A: Float[np.ndarray, "M d"], tol: float = _RANK_TOL
) -> Float[np.ndarray, "M r"]:
    """Orthonormal basis of the column span of ``A`` (pivoted QR; columns whose pivot is
    below ``tol`` × the largest one are dependent and dropped)."""
    A = np.asarray(A, dtype=np.float64)
    if A.ndim == 1:
        A = A[:, None]
    if A.shape[1] == 0 or not np.any(A):
        return np.zeros((A.shape[0], 0))
    q, r, _ = scipy.linalg.qr(A, mode="economic", pivoting=True)
    diag = np.abs(np.diag(r))
    rank = int(np.sum(diag > tol * diag[0]))
    return q[:, :rank]


def project_out(
    J_w: Float[np.ndarray, "M d"], y_w: Float[np.ndarray, "M ..."]
) -> Float[np.ndarray, "M ..."]:
    """``P⊥·y_w``: y_w [M] or [M, k] with its component in the span of ``J_w`` removed."""
    Q = orthonormal_basis(J_w)
    y = np.asarray(y_w, dtype=np.float64)
    return y - Q @ (Q.T @ y)


def score_statistic(
    r_w: Float[np.ndarray, " M"],
    G_w: Float[np.ndarray, "M ..."],
    J_w: Float[np.ndarray, "M d"],
    sigma2: float,
) -> float:
    """``S = r_wᵀ G⊥(G⊥ᵀG⊥)⁻¹G⊥ᵀ r_w / σ²`` with ``G⊥ = P⊥ G_w`` (G_w [M] or [M, k]); the
    pseudo-inverse drops directions of G that lie in the span of J (S = 0 if all do)."""
    G = np.asarray(G_w, dtype=np.float64)
    G = G[:, None] if G.ndim == 1 else G
    Q = orthonormal_basis(J_w)
    basis = _perp_basis(G[None], Q)[0]
    proj = basis.T @ np.asarray(r_w, dtype=np.float64)
    return float(proj @ proj / sigma2)


def score_pvalue(
    score: float | np.ndarray, k: int | np.ndarray, dof: int, external: int = 0
) -> np.ndarray:
    """p-value of a score with k regressors when σ̂² = ‖P⊥ r_w‖²/dof comes from the same
    residual: ``S/dof ~ Beta(k/2, (dof − k)/2)`` under H0 (k = 0 gives 1); with
    ``external`` = ν > 0, σ̂² is an independent estimate with ν degrees of freedom
    (``σ̂²/σ² ~ χ²_ν/ν``): ``S/k ~ F(k, ν)``."""
    s = np.asarray(score, dtype=np.float64)
    k = np.broadcast_to(np.asarray(k), s.shape)
    out = np.ones(s.shape)
    if external > 0:
        ok = k > 0
        out[ok] = stats.f.sf(s[ok] / k[ok], k[ok], external)
        return out
    ok = (k > 0) & (k < dof)
    x = np.clip(s / dof, 0.0, 1.0)
    out[ok] = stats.beta.sf(x[ok], k[ok] / 2.0, (dof - k[ok]) / 2.0)
    return out


def max_score_null(
    G_perp: Float[np.ndarray, "B M k"] | list[np.ndarray],
    n_mc: int,
    seed: int | np.random.Generator = 0,
    *,
    J_w: Float[np.ndarray, "M d"] | None = None,
    dof: int | None = None,
    external: int = 0,
) -> Float[np.ndarray, " n_mc"]:
    """Monte Carlo of ``max_b S_b`` under H0 for B regressor sets (already projected off J).

    ``z ~ N(0, I_M)`` (numpy PCG64 from ``seed``: same seed, same draws); ``S_b = ‖Q_bᵀ z‖²``
    with ``Q_b`` an orthonormal basis of ``G_perp[b]`` (zero or dependent columns dropped).
    With ``J_w`` given each draw is normalised by its own ``σ̂² = ‖P⊥ z‖²/dof`` (dof default
    ``M − rank J_w``), matching a statistic whose σ̂ comes from the same residual; with
    ``external`` = ν > 0 instead by an independent ``χ²_ν/ν`` (a σ̂ estimated elsewhere,
    :func:`fricjax.diagnose.select.forward_select`); without either, σ² = 1. Returns [n_mc].
    """
    stack = _orthonormal_stack(G_perp)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    m = stack.shape[1]
    fam = Family("", np.zeros(0), np.zeros(0), np.zeros(0), stack, None, None, None)
    Q = orthonormal_basis(J_w) if J_w is not None else None
    if Q is not None and dof is None:
        dof = m - Q.shape[1]
    out = np.empty(n_mc)
    for start in range(0, n_mc, _MC_BLOCK):  # blocks of draws, each one matrix product
        size = min(_MC_BLOCK, n_mc - start)
        Z = rng.standard_normal((m, size))
        scale = np.ones(size)
        if external > 0:
            scale = rng.chisquare(external, size) / external
        elif Q is not None:
            Zp = Z - Q @ (Q.T @ Z)
            scale = np.sum(Zp**2, axis=0) / dof
        out[start : start + size] = _family_scores(fam, Z).max(axis=0) / scale
    return out


# -- the baseband series and Ljung–Box --------------------------------------------------------


def baseband(wh: Whitener, z: Float[np.ndarray, "M ..."]) -> tuple[np.ndarray, float]:
    """The whitened vector read as a time series: ``(s [K', ...] complex, step [s])``.

    The kept bins' complex coefficients ``z_re + i·z_im`` (DC/Nyquist, which have no
    imaginary part, left out) in frequency order are the spectrum of the in-band whitened
    residual shifted down to 0 Hz; their unitary inverse DFT is that signal resampled at
    the band's own Nyquist rate (K' samples over the record, ``step = n·dt/K'``). It keeps
    where in time structure sits, and under H0 its samples are i.i.d. complex normal, which
    the plain inverse rfft (band-limited, so autocorrelated at every lag) would not be.
    """
    z = np.asarray(z, dtype=np.float64)
    K = wh.keep.size
    im_keep = wh.im_keep
    c = z[im_keep] + 1j * z[K:]
    s = np.fft.ifft(c, axis=0) * np.sqrt(c.shape[0])
    return s, wh.n * wh.dt / max(c.shape[0], 1)


def ljung_box_stat(s: np.ndarray, lags: int) -> np.ndarray:
    """Ljung–Box ``Q = 2n(n+2)·Σ_{h=1..H} |ρ_h|²/(n−h)`` of complex series s [n, ...]
    (≈ χ²_{2H} for white complex noise; ρ_h the lag-h autocorrelation, mean not removed)."""
    n = s.shape[0]
    spec = np.fft.fft(s, n=2 * n, axis=0)
    acov = np.fft.ifft(np.abs(spec) ** 2, axis=0)[: lags + 1]
    rho = acov[1:] / np.maximum(acov[:1].real, 1e-300)
    h = np.arange(1, lags + 1).reshape((-1,) + (1,) * (s.ndim - 1))
    return 2.0 * n * (n + 2) * np.sum(np.abs(rho) ** 2 / (n - h), axis=0)


def _ljung_box_p(stat: float, null: np.ndarray) -> float:
    # Scaled χ² matched to the mean and variance of the projected null (Satterthwaite):
    # exact tails where the Monte Carlo cannot resolve them, the projection accounted for.
    mean, var = float(np.mean(null)), float(np.var(null))
    scale, df = var / (2.0 * mean), 2.0 * mean**2 / var
    return float(stats.chi2.sf(stat / scale, df))


# -- maps -------------------------------------------------------------------------------------


def _orthonormal_stack(G: np.ndarray | list[np.ndarray]) -> np.ndarray:
    """[B, M, k] (or a list of [M, k_b]) -> per-bin orthonormal bases, zero columns where a
    bin has fewer independent columns than k."""
    if isinstance(G, list):
        mats = [g[:, None] if g.ndim == 1 else g for g in G]
        k = max(g.shape[1] for g in mats)
        G = np.stack([np.pad(g, ((0, 0), (0, k - g.shape[1]))) for g in mats])
    G = np.asarray(G, dtype=np.float64)
    if G.ndim == 2:
        G = G[:, :, None]
    return _perp_basis(G, np.zeros((G.shape[1], 0)))


def _perp_basis(G: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Orthonormal bases [B, M, k] of ``P⊥ G_b`` for G [B, M, k]. A direction counts when
    its singular value exceeds 1e-9 × the largest column norm of ``G_b`` itself: what the
    nuisance span explains is dropped rather than scored as noise."""
    Gp = G - np.einsum("mp,bpk->bmk", Q, np.einsum("mp,bmk->bpk", Q, G))
    U, sv, _ = np.linalg.svd(Gp, full_matrices=False)
    size = np.linalg.norm(G, axis=1).max(axis=1, keepdims=True)
    ok = (sv > _RANK_TOL * size) & (size > 0)
    return U * ok[:, None, :]


def _family_scores(fam: Family, Zp: np.ndarray) -> np.ndarray:
    """Unnormalised scores [B, N] of the projected whitened columns Zp [M, N]."""
    if fam.basis is not None:
        B, M, k = fam.basis.shape
        flat = fam.basis.transpose(0, 2, 1).reshape(B * k, M)
        return np.sum((flat @ Zp).reshape(B, k, -1) ** 2, axis=1)
    coef = np.einsum("bij,bjn->bin", fam.inv_sqrt, Zp[fam.rows])
    return np.sum(coef**2, axis=1)


def _dense_family(
    variable: str,
    wh: Whitener,
    Q: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    members: np.ndarray,
    sign: np.ndarray | None,
) -> Family:
    """Indicator regressors ``1_B`` (and ``1_B·sgn v`` when ``sign`` is given) of each bin."""
    cols = [members.T.astype(np.float64)]  # [n, B]
    if sign is not None:
        cols.append(members.T * sign[:, None])
    G = np.stack(cols, axis=-1)  # [n, B, k]
    n, B, k = G.shape
    Gw = wh(G.reshape(n, B * k)).reshape(wh.M, B, k).transpose(1, 0, 2)
    basis = _perp_basis(Gw, Q)
    rank = np.sum(np.any(basis != 0, axis=1), axis=1)
    return Family(variable, lo, hi, rank, basis, None, None, members)


def _quantile_bins(
    values: np.ndarray, mask: np.ndarray, n_bins: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Quantile bins of ``values[mask]``: (lo [B], hi [B], members [B, n]) or None."""
    vals = values[mask]
    nb = min(n_bins, vals.size // _MIN_PER_BIN)
    if nb < 1:
        return None
    edges = np.unique(np.quantile(vals, np.linspace(0.0, 1.0, nb + 1)))
    if edges.size < 2:
        edges = np.array([vals.min(), vals.max()])
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)
    B = edges.size - 1
    members = (idx[None, :] == np.arange(B)[:, None]) & mask[None, :]
    used = members.any(axis=1)
    return edges[:-1][used], edges[1:][used], members[used]


def _frequency_family(wh: Whitener, Q: np.ndarray) -> Family:
    K = wh.keep.size
    rows = np.zeros((K, 2), dtype=int)
    rows[:, 0] = np.arange(K)
    has_im = np.zeros(K, dtype=bool)
    has_im[wh.im_keep] = True
    rows[wh.im_keep, 1] = K + np.arange(wh.im_keep.size)
    A = Q[rows]  # [K, 2, p]
    gram = np.eye(2)[None] - np.einsum("bip,bjp->bij", A, A)
    # DC/Nyquist: a single regressor; the second slot is a dummy with no weight.
    gram[~has_im, 1, :] = 0.0
    gram[~has_im, :, 1] = 0.0
    lam, V = np.linalg.eigh(gram)
    ok = lam > _RANK_TOL
    inv = np.where(ok, 1.0 / np.sqrt(np.where(ok, lam, 1.0)), 0.0)
    inv_sqrt = np.einsum("bij,bj,bkj->bik", V, inv, V)
    df = 1.0 / (wh.n * wh.dt)
    return Family(
        "frequency",
        wh.freqs - df / 2,
        wh.freqs + df / 2,
        ok.sum(axis=1),
        None,
        rows,
        inv_sqrt,
        None,
    )


def _families(problem: Problem, wh: Whitener, Q: np.ndarray, n_bins: int) -> list[Family]:
    t, x, v, a = (
        np.asarray(arr, dtype=np.float64) for arr in (problem.t, problem.x, problem.v, problem.a)
    )
    n = t.shape[0]
    sign = np.sign(v)
    out: list[Family] = []
    edges = np.linspace(t[0], t[-1], n_bins + 1)
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, n_bins - 1)
    members = idx[None, :] == np.arange(n_bins)[:, None]
    out.append(_dense_family("time", wh, Q, edges[:-1], edges[1:], members, None))
    everywhere = np.ones(n, dtype=bool)
    for variable, values, mask, signed in (
        ("velocity+", v, v > 0, False),
        ("velocity-", v, v < 0, False),
        ("position", x, everywhere, True),
        ("acceleration", a, everywhere, False),
    ):
        bins = _quantile_bins(values, mask, n_bins)
        if bins is None:
            continue
        lo, hi, mem = bins
        out.append(_dense_family(variable, wh, Q, lo, hi, mem, sign if signed else None))
    out.append(_frequency_family(wh, Q))
    return out


# -- cross-correlation tests --------------------------------------------------------------

# Unit-variance noise records drawn to measure the errors-in-variables terms of CrossTest.
_EIV_DRAWS = 200
# A cross test is reported as untestable (NaN) when the signal's own whitened noise makes up
# more than this share of its projected norm²: the first-order correction then leaves a bias
# of the order of the noise (paper twin, a: 83 % noise, corrected z still 1.7 ± 0.1 off).
_EIV_MAX = 0.1


def _cross_tests(
    problem: Problem, wh: Whitener, Q: np.ndarray, rng: np.random.Generator
) -> dict[str, CrossTest | None]:
    settings = problem.preprocess
    assert settings is not None  # make_whitener has checked it
    n, trim = problem.n, settings.trim
    n_full = n + 2 * trim
    t_full = np.arange(n_full) * wh.dt
    E = rng.standard_normal((_EIV_DRAWS, n_full))
    Lv = np.empty((n, _EIV_DRAWS))
    La = np.empty((n, _EIV_DRAWS))
    for j in range(_EIV_DRAWS):  # derivatives() is 1-D; one call per noise record
        d = derivatives(t_full, E[j], settings)
        Lv[:, j], La[:, j] = d.v, d.a
    v = np.asarray(problem.v, dtype=np.float64)
    signals = {
        "v": (v, Lv),
        "x": (np.asarray(problem.x, dtype=np.float64), E[:, trim : trim + n].T),
        "a": (np.asarray(problem.a, dtype=np.float64), La),
        "|v|": (np.abs(v), np.sign(v)[:, None] * Lv),
        "sgn v": (np.sign(v), None),
    }
    gain_v, _ = noise_gains(settings, 1.0 / wh.dt)
    U = wh(wh.mass * La - wh.damping * Lv)
    Up = U - Q @ (Q.T @ U)
    out: dict[str, CrossTest | None] = {}
    for name, (g, noise) in signals.items():
        gw = wh(g)
        gp = gw - Q @ (Q.T @ gw)
        if np.linalg.norm(gp) <= _RANK_TOL * max(float(np.linalg.norm(gw)), 1e-300):
            out[name] = None
            continue
        if noise is None:
            kept = ~wh.excluded
            speed = float(np.min(np.abs(v[kept]))) / gain_v if np.any(kept) else np.inf
            out[name] = CrossTest(gp, 0.0, 0.0, 0.0, speed)
            continue
        W_ = wh(noise)
        Wp = W_ - Q @ (Q.T @ W_)
        q = np.sum(Wp * Up, axis=0)
        noise2 = float(np.sum(Wp**2)) / _EIV_DRAWS
        out[name] = CrossTest(gp, float(q.mean()), float(q.var()), noise2, np.inf)
    return out


def _cross_p(test: CrossTest | None, rp: np.ndarray, sigma2: float, dof: int) -> float:
    if test is None:
        return 1.0
    if sigma2 * test.noise > _EIV_MAX * float(test.gp @ test.gp):
        return float("nan")
    if test.flip_speed < 4.0 * np.sqrt(sigma2):
        return float("nan")
    signal2 = max(float(test.gp @ test.gp) - sigma2 * test.noise, 0.0)
    var = sigma2 * signal2 + sigma2**2 * test.var_q
    if var <= 0:
        return 1.0
    z = (float(test.gp @ rp) - sigma2 * test.bias) / np.sqrt(var)
    return float(2.0 * stats.t.sf(abs(z), dof))


# -- the plan and the report ---------------------------------------------------------------


#: Noise models of :func:`default_whitener`.
NOISE_MODELS = ("auto", "position", "spectral")


def resolve_noise(problem: Problem, noise: str = "auto") -> str:
    """``"auto"`` -> ``"spectral"`` when the model's drive is a recorded input (its noise,
    and the loop's, enter the residual as force, with a colour the displacement noise
    model does not describe), else ``"position"`` (the displacement sensor is the only
    noisy measurement, as on the paper twin)."""
    if noise not in NOISE_MODELS:
        raise FricjaxError(
            f"{where(problem.source or None, '[diagnose].noise')}: unknown noise model "
            f"{noise!r} (valid: {', '.join(NOISE_MODELS)})"
        )
    if noise != "auto":
        return noise
    return "spectral" if needs_input(problem.model) else "position"


def static_level(problem: Problem, theta: Float[np.ndarray, " d"]) -> float:
    """Largest friction limit at rest over the record [N] (0: nothing sticks at theta)."""
    p = problem.spec.unflatten(jnp.asarray(theta, dtype=jnp.float64))
    jump = np.asarray(problem.model.static(p, problem.signals, jnp.ones(problem.n)))
    return float(np.max(np.abs(jump)))


def default_whitener(
    problem: Problem,
    theta: Float[np.ndarray, " d"],
    noise: str = "auto",
    sigma_x: float | None = None,
) -> Whitener:
    """Whitener with the linearised damping at theta; when the model's friction jumps at
    v = 0 (nonzero static friction at theta), the samples near velocity reversals are
    excluded (|v| < 4·σ_v, :func:`~fricjax.diagnose.evidence.near_rest_band` with the
    record's own σ̂_x, ``sigma_x`` [m], by default :func:`~fricjax.diagnose.evidence.
    record_noise` of ``problem``): there the
    sign flips of the Coulomb term dominate the low bins (:mod:`fricjax.diagnose.whiten`).
    When ``problem.rest`` marks the samples at rest (the residual then uses the stick/slip
    rule there), those are the samples excluded. They stay excluded although the rule
    removes the sign flips: a quarter to a half of them slide slowly (|v| < 4·σ_v) rather
    than stick, where the rule is wrong by up to twice the friction level. Measured on the
    1 s paper twin at its truth with Fs, Fc ×1.6 (123 of 213 such samples sliding): keeping
    the runs' interiors in the test raised RSS/dof from 1.56 to 1.79.

    ``noise`` (:func:`resolve_noise`): ``"position"`` = displacement noise only (exact
    whitener); ``"spectral"`` scales every bin by the residual's own smoothed spectrum at
    theta (:func:`~fricjax.diagnose.whiten.noise_spectrum`); the reversal mask still comes
    from the displacement noise σ̂_x (it is about sign flips of v, which only x-noise
    causes)."""
    noise = resolve_noise(problem, noise)
    c = linear_damping(problem, theta)
    first = make_whitener(problem, damping=c)
    r = np.asarray(problem.residual(theta))
    spectrum = None
    unmasked = first
    if noise == "spectral":
        dt = float((problem.t[-1] - problem.t[0]) / (problem.n - 1))
        spectrum = noise_spectrum(r, dt)
        unmasked = make_whitener(problem, spectrum=spectrum)
    static = static_level(problem, theta)
    if static == 0.0:
        return unmasked
    sigma = record_noise(problem).sigma_x if sigma_x is None else sigma_x
    # The samples marked at rest are these same samples (with_rest), kept as marked so that
    # the parts of a held-out split and the whole record agree on them.
    mask = near_rest_band(problem, sigma).mask if problem.rest is None else problem.rest
    # A flip of sgn v puts a spike of up to 2·|F_static| on a masked sample. Only the
    # whitened directions where such spikes would show are projected out, so a stick phase
    # costs a few degrees of freedom instead of one per sample; at most 0.4·M of them,
    # the largest first (something must be left to test).
    # (the spectral whitener's vectors are already in noise units, the position one's in m)
    spike = 2.0 * static / (1.0 if spectrum is not None else sigma)
    limit = int(0.4 * unmasked.M)
    return make_whitener(
        problem, damping=c, exclude=mask, spectrum=spectrum, spike=spike, max_rank=limit
    )


@eqx.filter_jit(compiler_options=FAST_COMPILE)
def compiled_jacfwd(fn: Any, theta: Array) -> Array:
    """``jax.jacfwd(fn)(theta)`` under ``eqx.filter_jit`` (the arrays inside ``fn`` are
    traced, not baked in) with the search's fast-compile options: the diagnosis' Jacobians
    run once per record and candidate, so compile time is what counts. Shared by
    :func:`jacobian` and the selection's whitened Jacobians (one compilation cache)."""
    return jax.jacfwd(fn)(theta)


def jacobian(problem: Problem, theta: Float[np.ndarray, " d"]) -> Float[np.ndarray, "n d"]:
    """``∂r/∂θ`` [n, d] of the equation-error residual (jax.jacfwd; one compilation per
    model, spec and record length)."""
    theta = jnp.asarray(theta, dtype=jnp.float64)
    if theta.shape[0] == 0:
        return np.zeros((problem.n, 0))
    return np.asarray(compiled_jacfwd(problem.residual_fn, theta))


class TooShortToLocate(FricjaxError):
    """The fitted directions leave the residual maps fewer than 2 degrees of freedom."""


def locate_plan(
    problem: Problem,
    theta: Float[np.ndarray, " d"],
    *,
    whitener: Whitener | None = None,
    n_bins: int = 20,
    n_mc: int = 2000,
    seed: int | np.random.Generator = 0,
    lags: int = 20,
) -> LocatePlan:
    """Regressors, nuisance basis and Monte Carlo nulls of ``problem`` at ``theta``.

    ``whitener`` default: :func:`default_whitener`.
    """
    src = problem.source or problem.name or None
    if n_bins < 1 or n_mc < 10:
        raise FricjaxError(f"{where(src, 'n_bins, n_mc')}: need n_bins >= 1, n_mc >= 10")
    wh = whitener or default_whitener(problem, theta)
    if wh.n != problem.n:
        raise FricjaxError(
            f"{where(src, 'whitener')}: built for {wh.n} samples, the problem has {problem.n}"
        )
    J_w = wh(jacobian(problem, theta))
    Q = orthonormal_basis(np.concatenate([J_w, wh.N], axis=1))
    dof = wh.M - Q.shape[1]
    if dof < 2:
        raise TooShortToLocate(
            f"{where(src, 'params')}: {Q.shape[1]} fitted directions leave {dof} of the "
            f"{wh.M} whitened degrees of freedom; the record is too short to locate"
        )
    families = _families(problem, wh, Q, n_bins)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    cross = _cross_tests(problem, wh, Q, rng)
    lags = int(min(lags, max(1, (wh.M - wh.keep.size) // 4)))
    null = {f.variable: np.empty(n_mc) for f in families}
    lb_null = np.empty(n_mc)
    for start in range(0, n_mc, _MC_BLOCK):  # blocks of draws, each a few matrix products
        size = min(_MC_BLOCK, n_mc - start)
        Z = rng.standard_normal((wh.M, size))
        Zp = Z - Q @ (Q.T @ Z)
        sigma2 = np.sum(Zp**2, axis=0) / dof
        for fam in families:
            null[fam.variable][start : start + size] = _family_scores(fam, Zp).max(axis=0) / sigma2
        lb_null[start : start + size] = ljung_box_stat(baseband(wh, Zp)[0], lags)
    return LocatePlan(wh, Q, dof, families, null, cross, lags, lb_null)


def _coef(fam: Family, V: np.ndarray) -> np.ndarray:
    """``basis_bᵀ V`` [B, k, N] for V [M, N] (V orthogonal to the nuisance span)."""
    if fam.basis is not None:
        return np.einsum("bmk,mn->bkn", fam.basis, V)
    return np.einsum("bij,bjn->bin", fam.inv_sqrt, V[fam.rows])


def _step_down(
    fam: Family, Q: np.ndarray, rp: np.ndarray, sigma2: float, threshold: float
) -> np.ndarray:
    """Significant bins [B] bool, selected one at a time: the best bin's score, conditional
    on the bins already selected (their regressors added to the nuisance), must exceed the
    map's null-max threshold. The first step is the max test itself (family-wise α on a null
    record); the later ones stop a strong effect from lighting up every bin correlated with
    it (a 40 N force over 84 ms otherwise made bins 0.3 s away significant)."""
    B = fam.lo.shape[0]
    k = fam.basis.shape[2] if fam.basis is not None else fam.inv_sqrt.shape[2]
    if fam.basis is not None:
        live = np.linalg.norm(fam.basis, axis=1) > 0  # [B, k]
    else:
        live = np.linalg.norm(fam.inv_sqrt, axis=1) > 0
    eye = np.eye(k)[None] * live[:, None, :] * live[:, :, None]
    chosen = np.zeros(B, dtype=bool)
    C = np.zeros((rp.shape[0], 0))
    resid = rp
    for _ in range(B):
        coef = _coef(fam, resid[:, None])[:, :, 0]  # [B, k]
        D = _coef(fam, C)  # [B, k, c]
        lam, V = np.linalg.eigh(eye - D @ D.transpose(0, 2, 1))
        inv = np.where(lam > _RANK_TOL, 1.0 / np.where(lam > _RANK_TOL, lam, 1.0), 0.0)
        proj = np.einsum("bji,bj->bi", V, coef)
        scores = np.sum(inv * proj**2, axis=1) / sigma2
        scores[chosen] = -np.inf
        b = int(np.argmax(scores))
        if not scores[b] > threshold:
            break
        chosen[b] = True
        C = orthonormal_basis(np.concatenate([C, _bin_basis(fam, Q, b)], axis=1))
        resid = rp - C @ (C.T @ rp)
    return chosen


def _bin_basis(fam: Family, Q: np.ndarray, b: int) -> np.ndarray:
    """The whitened, projected regressors [M, k] of bin b."""
    if fam.basis is not None:
        return fam.basis[b]
    E = np.zeros((Q.shape[0], fam.rows.shape[1]))
    E[fam.rows[b], np.arange(fam.rows.shape[1])] = 1.0
    return (E - Q @ (Q[fam.rows[b]].T)) @ fam.inv_sqrt[b]


def locate_whitened(
    plan: LocatePlan,
    r_w: Float[np.ndarray, " M"],
    *,
    residual: Float[np.ndarray, " n"] | None = None,
    alpha: float = 0.01,
) -> LocateReport:
    """The report for a whitened residual ``r_w`` (``residual``, the unwhitened one [N],
    only fills ``MapBin.mean_residual``; NaN without it)."""
    if not 0.0 < alpha < 1.0:
        raise FricjaxError(f"{where('locate', 'alpha')}: must be in (0, 1), got {alpha!r}")
    wh, Q, dof = plan.whitener, plan.Q, plan.dof
    r_w = np.asarray(r_w, dtype=np.float64)
    rp = r_w - Q @ (Q.T @ r_w)
    sigma2 = float(rp @ rp) / dof
    if sigma2 <= 0:
        raise FricjaxError(f"{where('locate', 'residual')}: zero after the base fit's span")
    r = None if residual is None else np.asarray(residual, dtype=np.float64)
    amp = None if r is None else 2.0 * np.abs(np.fft.rfft(r)[wh.keep]) / wh.n
    bins: list[MapBin] = []
    family_p: dict[str, float] = {}
    for fam in plan.families:
        scores = _family_scores(fam, rp[:, None])[:, 0] / sigma2
        p = score_pvalue(scores, fam.rank, dof)
        null = plan.null_max[fam.variable]
        threshold = float(np.quantile(null, 1.0 - alpha))
        family_p[fam.variable] = float((1 + np.sum(null >= scores.max())) / (1 + null.size))
        chosen = _step_down(fam, Q, rp, sigma2, threshold)
        if fam.members is not None:
            counts = fam.members.sum(axis=1)
            means = np.full(scores.shape, np.nan) if r is None else (fam.members @ r) / counts
        else:
            means = np.full(scores.shape, np.nan) if amp is None else amp
        for b in range(scores.shape[0]):
            bins.append(
                MapBin(
                    fam.variable,
                    float(fam.lo[b]),
                    float(fam.hi[b]),
                    float(means[b]),
                    float(scores[b]),
                    float(p[b]),
                    bool(chosen[b]),
                )
            )
    significant = sorted((b for b in bins if b.significant), key=lambda b: (b.p_value, -b.score))
    crosscorr = {name: _cross_p(test, rp, sigma2, dof) for name, test in plan.cross.items()}
    lb = float(ljung_box_stat(baseband(wh, rp)[0], plan.lags))
    return LocateReport(
        bins=bins,
        significant=significant,
        ljung_box_p=_ljung_box_p(lb, plan.lb_null),
        ljung_box_stat=lb,
        crosscorr=crosscorr,
        sigma=float(np.sqrt(sigma2)),
        family_p=family_p,
    )


def map_scores(plan: LocatePlan, R_w: Float[np.ndarray, "M N"]) -> dict[str, np.ndarray]:
    """Scores [B, N] of each map for N whitened residuals at once (each normalised by its
    own σ̂²): the vectorised core of :func:`locate_whitened`, for calibration studies."""
    R = np.asarray(R_w, dtype=np.float64)
    Rp = R - plan.Q @ (plan.Q.T @ R)
    sigma2 = np.sum(Rp**2, axis=0) / plan.dof
    return {f.variable: _family_scores(f, Rp) / sigma2 for f in plan.families}


def locate(
    problem: Problem,
    theta: Float[np.ndarray, " d"],
    *,
    whitener: Whitener | None = None,
    n_bins: int = 20,
    alpha: float = 0.01,
    n_mc: int = 2000,
    seed: int | np.random.Generator = 0,
) -> LocateReport:
    """Mismatch maps and residual tests of ``problem`` at ``theta`` (module docstring).

    Args:
        problem: the preprocessed recording and base model.
        theta: base parameters [d] (normally the fit).
        whitener: default :func:`default_whitener` (linearised damping at theta; samples
            near reversals excluded when the friction jumps at v = 0).
        n_bins: bins per map (time: equal intervals; v, x, a: quantiles).
        alpha: family-wise false-alarm rate of each map's ``significant`` bins.
        n_mc: Monte Carlo draws of each map's null maximum.
        seed: numpy seed (or Generator) of the draws; same seed, same report.
    """
    plan = locate_plan(problem, theta, whitener=whitener, n_bins=n_bins, n_mc=n_mc, seed=seed)
    r = problem.residual(theta)
    return locate_whitened(plan, plan.whitener(r), residual=r, alpha=alpha)
