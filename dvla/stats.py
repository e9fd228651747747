"""Statistics the orchestrator and the learners share, free of torch (the CLI's tools import them)."""

from __future__ import annotations

import math


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a success rate (95 % for the default ``z``); (0, 1) for n = 0.
    Unlike the normal approximation it stays inside [0, 1] and is honest at 0 or n successes."""
    if n <= 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def successes_to_pass(episodes: int, until_success: float, success_on: str = "rate") -> int | None:
    """The fewest successes out of ``episodes`` with which one evaluation clears the stop rule's
    ``until_success`` (compared with the success rate, or with its Wilson ``lower_bound``), as the
    orchestrator compares them; None if not even ``episodes`` successes clear it."""
    if success_on not in ("rate", "lower_bound"):
        raise ValueError(f"success_on: expected 'rate' or 'lower_bound', got {success_on!r}")
    for k in range(episodes + 1):
        value = k / episodes if success_on == "rate" else wilson_interval(k, episodes)[0]
        if value >= until_success:
            return k
    return None


def pass_probability(p: float, episodes: int, until_success: float, consecutive: int = 1,
                     success_on: str = "rate") -> float:
    """Exact binomial probability that a policy of true success rate ``p`` clears the stop rule
    on ``consecutive`` evaluations of ``episodes`` independent episodes each (docs/evaluation.md)."""
    k = successes_to_pass(episodes, until_success, success_on)
    if k is None:
        return 0.0
    one = sum(math.comb(episodes, i) * p ** i * (1 - p) ** (episodes - i) for i in range(k, episodes + 1))
    return one ** consecutive


#: the rules of the table in docs/evaluation.md: (episodes, until_success, consecutive, success_on)
RULES = (
    (16, 0.8, 3, "rate"),
    (64, 0.8, 1, "rate"),
    (64, 0.8, 2, "rate"),
    (128, 0.7, 1, "lower_bound"),
    (64, 0.7, 2, "lower_bound"),
    (128, 0.75, 1, "lower_bound"),
)


def pass_table(rules: tuple[tuple[int, float, int, str], ...] = RULES,
               rates: tuple[float, ...] = (0.65, 0.70, 0.75, 0.80, 0.85, 0.90, 0.95)) -> str:
    """docs/evaluation.md's table of pass probabilities, as Markdown."""
    head = ["true *p*"] + [f"{n} ep., {'lower bound' if on == 'lower_bound' else 'rate'} >= {t}"
                           + (f", {c} in a row" if c > 1 else "") for n, t, c, on in rules]
    need = ["successes needed"] + [f"{successes_to_pass(n, t, on)} of {n}" for n, t, _c, on in rules]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head), "| " + " | ".join(need) + " |"]
    for p in rates:
        lines.append(f"| {p:.2f} | " + " | ".join(f"{pass_probability(p, n, t, c, on):.3f}" for n, t, c, on in rules) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(pass_table())
