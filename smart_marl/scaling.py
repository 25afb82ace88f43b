"""Scaling laws: how the held-out next-token loss moves with model size N (parameters) and data size D
(training target tokens), the paper's Figure 4 claim (a power law in N, exponent -0.157), measured with the
project's own trainer.

What comes in: points (x, loss) from training runs (``benchmarks/scaling_laws.py`` makes them). What goes out:
:func:`fit_power_law`, a fit of ``L(x) = E + A * x ** -alpha`` (an irreducible term E >= 0) by least squares
in log space, ``log L_i - log(E + A x_i^-alpha)``, with each parameter's standard error from the Gauss-Newton
covariance ``s^2 (J^T J)^-1`` (``s^2`` the residual variance over ``n - 3`` degrees of freedom); and
:func:`fit_pure_power_law`, ``L = A x ** -alpha`` (a straight line in log-log: the paper's form), with the
ordinary least-squares standard error of its slope. numpy only.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

PAPER_EXPONENT = -0.157
"""The exponent of the paper's fit of held-out loss against parameters (SMART, NeurIPS 2024, Figure 4)."""


@dataclass
class PowerLawFit:
    """``L(x) = irreducible + coefficient * x ** -alpha``; ``exponent`` is ``-alpha`` (the paper's sign)."""

    exponent: float
    exponent_se: float
    coefficient: float
    irreducible: float
    irreducible_se: float
    points: int
    dof: int  # degrees of freedom of the residuals (points - fitted parameters)
    rms_log_residual: float
    form: str  # "E + A x^-alpha" or "A x^-alpha"

    def predict(self, x) -> np.ndarray:
        return self.irreducible + self.coefficient * np.asarray(x, float) ** self.exponent

    def to_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def _check(x, loss) -> tuple[np.ndarray, np.ndarray]:
    x, loss = np.asarray(x, float), np.asarray(loss, float)
    if x.shape != loss.shape or x.ndim != 1:
        raise ValueError(f"x and loss must be two equally long lists, got shapes {x.shape} and {loss.shape}")
    if len(x) < 2 or not (np.isfinite(x).all() and np.isfinite(loss).all() and (x > 0).all() and (loss > 0).all()):
        raise ValueError("a power-law fit needs at least 2 points, every x and loss finite and > 0")
    if len(np.unique(x)) < 2:
        raise ValueError("a power-law fit needs at least 2 distinct x")
    return x, loss


def fit_pure_power_law(x, loss) -> PowerLawFit:
    """``log L = log A - alpha log x`` by ordinary least squares; the slope's standard error (0 with 2 points)."""
    x, loss = _check(x, loss)
    lx, ly = np.log(x), np.log(loss)
    design = np.stack([np.ones_like(lx), lx], 1)
    coef, *_ = np.linalg.lstsq(design, ly, rcond=None)
    resid = ly - design @ coef
    dof = len(x) - 2
    s2 = float(resid @ resid) / dof if dof > 0 else 0.0
    cov = s2 * np.linalg.inv(design.T @ design)
    return PowerLawFit(exponent=float(coef[1]), exponent_se=float(np.sqrt(cov[1, 1])), coefficient=float(np.exp(coef[0])),
                       irreducible=0.0, irreducible_se=0.0, points=len(x), dof=dof,
                       rms_log_residual=float(np.sqrt(np.mean(resid ** 2))), form="A x^-alpha")


def _residuals(theta: np.ndarray, lx: np.ndarray, ly: np.ndarray) -> np.ndarray:
    """theta = (log A, alpha, log E): log L - log(E + A x^-alpha)."""
    log_a, alpha, log_e = theta
    return ly - np.logaddexp(log_e, log_a - alpha * lx)


def _jacobian(theta: np.ndarray, lx: np.ndarray) -> np.ndarray:
    """d residual / d theta, analytic: with p = A x^-alpha / (E + A x^-alpha), the fraction of L above E."""
    log_a, alpha, log_e = theta
    p = 1.0 / (1.0 + np.exp(log_e - (log_a - alpha * lx)))
    return -np.stack([p, -p * lx, 1.0 - p], 1)


def fit_power_law(x, loss, iterations: int = 200) -> PowerLawFit:
    """``L = E + A x^-alpha`` in log space (Levenberg-Marquardt from the best start of a grid over alpha and E),
    with standard errors from ``s^2 (J^T J)^-1``; with 3 points (no degree of freedom left) the errors are
    infinite, and the pure power law (:func:`fit_pure_power_law`) is the form to read."""
    x, loss = _check(x, loss)
    lx, ly = np.log(x), np.log(loss)
    best = None
    for alpha in np.linspace(0.01, 2.0, 60):  # a start: for fixed alpha and E, log A is the mean gap
        for share in (0.0, 0.25, 0.5, 0.75, 0.9, 0.97):
            e = share * loss.min()
            above = np.clip(loss - e, 1e-12, None)
            log_a = float(np.mean(np.log(above) + alpha * lx))
            theta = np.array([log_a, alpha, np.log(max(e, 1e-12))])
            cost = float(np.sum(_residuals(theta, lx, ly) ** 2))
            if best is None or cost < best[0]:
                best = (cost, theta)
    cost, theta = best
    damping = 1e-3
    for _ in range(iterations):
        r, jac = _residuals(theta, lx, ly), _jacobian(theta, lx)
        jtj = jac.T @ jac
        step = np.linalg.solve(jtj + damping * np.diag(np.diag(jtj) + 1e-12), -jac.T @ r)
        trial = theta + step
        trial[2] = max(trial[2], np.log(1e-12))  # E >= 0 (as exp of a bounded log)
        new = float(np.sum(_residuals(trial, lx, ly) ** 2))
        if new < cost:
            theta, cost, damping = trial, new, max(damping / 3, 1e-9)
            if np.abs(step).max() < 1e-10:
                break
        else:
            damping *= 4
            if damping > 1e8:
                break
    r, jac = _residuals(theta, lx, ly), _jacobian(theta, lx)
    dof = len(x) - 3
    if dof > 0:
        cov = float(r @ r) / dof * np.linalg.pinv(jac.T @ jac)
        alpha_se = float(np.sqrt(max(cov[1, 1], 0.0)))
        e_se = float(np.exp(theta[2]) * np.sqrt(max(cov[2, 2], 0.0)))  # delta method on E = exp(log E)
    else:
        alpha_se = e_se = float("inf")
    return PowerLawFit(exponent=-float(theta[1]), exponent_se=alpha_se, coefficient=float(np.exp(theta[0])),
                       irreducible=float(np.exp(theta[2])), irreducible_se=e_se, points=len(x), dof=dof,
                       rms_log_residual=float(np.sqrt(np.mean(r ** 2))), form="E + A x^-alpha")


__all__ = ["PAPER_EXPONENT", "PowerLawFit", "fit_power_law", "fit_pure_power_law"]
