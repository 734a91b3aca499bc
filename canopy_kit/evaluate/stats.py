"""Agreement statistics between an estimate and a reference, one value per item.

Used for the paper's Table I (LiDAR volumes vs drone sphere volumes) and for every later
comparison of LiDAR against aerial volumes. Conventions: the difference is always
``estimate - reference`` (positive = overestimate); percentages are of the reference.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from canopy_kit.errors import InputError

#: Two-sided 95 % normal quantile used for Bland-Altman limits of agreement.
Z_95 = 1.959963984540054


def _pair(
    estimate: ArrayLike, reference: ArrayLike, *, min_n: int = 1, nonzero_reference: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Validate and convert a pair of equally long 1-D finite arrays."""
    est = np.asarray(estimate, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    for name, arr in (("estimate", est), ("reference", ref)):
        if arr.ndim != 1:
            raise InputError(f"{name}: expected a 1-D array, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            bad = int(np.flatnonzero(~np.isfinite(arr))[0])
            raise InputError(f"{name}: value at index {bad} is not finite ({arr[bad]})")
    if est.shape != ref.shape:
        raise InputError(f"estimate and reference differ in length ({est.size} vs {ref.size})")
    if est.size < min_n:
        raise InputError(f"need at least {min_n} pairs, got {est.size}")
    if nonzero_reference and np.any(ref == 0):
        bad = int(np.flatnonzero(ref == 0)[0])
        raise InputError(f"reference: value at index {bad} is zero; percentages undefined")
    return est, ref


def percent_errors(estimate: ArrayLike, reference: ArrayLike) -> NDArray[np.float64]:
    """Signed percentage error per item: ``(estimate - reference) / reference * 100``."""
    est, ref = _pair(estimate, reference, nonzero_reference=True)
    return (est - ref) / ref * 100.0


def mape(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Mean absolute percentage error (%), the mean of ``|estimate - reference| / reference``."""
    return float(np.mean(np.abs(percent_errors(estimate, reference))))


def mean_bias(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Mean signed difference ``estimate - reference`` (in the inputs' unit)."""
    est, ref = _pair(estimate, reference)
    return float(np.mean(est - ref))


def mean_percent_bias(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Mean signed percentage error (%); positive means the estimate runs high."""
    return float(np.mean(percent_errors(estimate, reference)))


def rmse(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Root-mean-square difference (in the inputs' unit)."""
    est, ref = _pair(estimate, reference)
    return float(np.sqrt(np.mean((est - ref) ** 2)))


def r_squared(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Coefficient of determination of the estimate as a predictor of the reference.

    ``1 - sum((est - ref)^2) / sum((ref - mean(ref))^2)``: 1 is perfect, 0 is no better
    than predicting the mean reference, negative is worse. Unlike Pearson r², it is
    penalised by bias and by a slope different from 1.
    """
    est, ref = _pair(estimate, reference, min_n=2)
    ss_tot = float(np.sum((ref - ref.mean()) ** 2))
    if ss_tot == 0.0:
        raise InputError("reference: all values are equal; R² is undefined")
    return 1.0 - float(np.sum((est - ref) ** 2)) / ss_tot


def pearson_r2(estimate: ArrayLike, reference: ArrayLike) -> float:
    """Square of the Pearson correlation between estimate and reference (scale-free)."""
    est, ref = _pair(estimate, reference, min_n=2)
    if np.all(est == est[0]) or np.all(ref == ref[0]):
        raise InputError("estimate or reference is constant; Pearson r is undefined")
    return float(np.corrcoef(est, ref)[0, 1] ** 2)


@dataclass(frozen=True)
class BlandAltman:
    """Bland-Altman agreement: mean difference and 95 % limits of agreement."""

    n: int
    mean_difference: float
    sd_difference: float
    lower_limit: float
    upper_limit: float


def bland_altman(estimate: ArrayLike, reference: ArrayLike) -> BlandAltman:
    """Mean of ``estimate - reference`` and limits ``mean ± 1.96 SD`` (SD with ddof=1)."""
    est, ref = _pair(estimate, reference, min_n=2)
    diff = est - ref
    mean = float(diff.mean())
    sd = float(diff.std(ddof=1))
    return BlandAltman(
        n=int(diff.size),
        mean_difference=mean,
        sd_difference=sd,
        lower_limit=mean - Z_95 * sd,
        upper_limit=mean + Z_95 * sd,
    )


@dataclass(frozen=True)
class Agreement:
    """Every agreement statistic of one estimate against one reference."""

    n: int
    mape_pct: float
    bias: float
    bias_pct: float
    rmse: float
    r_squared: float
    pearson_r2: float
    bland_altman: BlandAltman

    def as_dict(self) -> dict[str, Any]:
        """Flat dictionary (Bland-Altman fields prefixed ``ba_``) for tables and JSON."""
        out = {k: v for k, v in asdict(self).items() if k != "bland_altman"}
        out.update({f"ba_{k}": v for k, v in asdict(self.bland_altman).items() if k != "n"})
        return out


def agreement(estimate: ArrayLike, reference: ArrayLike) -> Agreement:
    """Compute MAPE, bias (unit and %), RMSE, R², Pearson r² and Bland-Altman at once."""
    est, ref = _pair(estimate, reference, min_n=2, nonzero_reference=True)
    return Agreement(
        n=int(est.size),
        mape_pct=mape(est, ref),
        bias=mean_bias(est, ref),
        bias_pct=mean_percent_bias(est, ref),
        rmse=rmse(est, ref),
        r_squared=r_squared(est, ref),
        pearson_r2=pearson_r2(est, ref),
        bland_altman=bland_altman(est, ref),
    )
