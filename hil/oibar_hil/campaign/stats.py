"""Success rates with exact (Clopper-Pearson) binomial bounds.

``rate(k, n)`` gives the two-sided interval at ``confidence`` and the one-sided lower bound at
the same confidence (the figure a claim "at least p with 95 % confidence" rests on: with no
failure in n missions it is (1 - confidence)^(1/n), 0.990 for 300 at 95 %).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Rate:
    successes: int
    trials: int
    confidence: float
    low: float  # two-sided exact interval at `confidence`
    high: float
    lower_bound: float  # one-sided exact lower bound at `confidence`

    @property
    def rate(self) -> float:
        return self.successes / self.trials if self.trials else float("nan")

    def text(self) -> str:
        if not self.trials:
            return "no missions"
        c = round(100 * self.confidence)
        return (
            f"{self.successes}/{self.trials} = {100 * self.rate:.2f} % "
            f"({c} % CI {100 * self.low:.2f}-{100 * self.high:.2f} %; "
            f">= {100 * self.lower_bound:.2f} % with {c} % confidence)"
        )


def rate(successes: int, trials: int, confidence: float = 0.95) -> Rate:
    """Clopper-Pearson: scipy.stats.binomtest(k, n).proportion_ci(method="exact")."""
    if trials < 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials, got {successes}/{trials}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if trials == 0:
        return Rate(0, 0, confidence, 0.0, 1.0, 0.0)
    from scipy.stats import binomtest

    test = binomtest(successes, trials)
    two = test.proportion_ci(confidence_level=confidence, method="exact")
    # The one-sided bound at c is the lower end of the two-sided interval at 2c - 1.
    one = test.proportion_ci(confidence_level=2.0 * confidence - 1.0, method="exact")
    return Rate(successes, trials, confidence, float(two.low), float(two.high), float(one.low))


def missions_for_claim(rate_claim: float, confidence: float = 0.95) -> int:
    """Missions without a failure needed to show success >= rate_claim at that confidence."""
    import math

    if not 0.0 < rate_claim < 1.0:
        raise ValueError("rate_claim must be in (0, 1)")
    return math.ceil(math.log(1.0 - confidence) / math.log(rate_claim))
