"""``benchmarks/critic_gap_ranking.py``: a learned trigger's and its critic's ranking against predictive triggering."""

from __future__ import annotations

SCRIPT = "critic_gap_ranking.py"


def test_a_policy_over_options_that_imitates_predictive_triggering_ranks_as_it_does(run_benchmark) -> None:
    """The committed imitation of predictive triggering puts the same agent-steps on top; its young critic does not."""
    arm = "predictive_imitated_90"
    done = run_benchmark(SCRIPT, "benchmarks/studies/linear_lqr_rate", "--arms", arm, "--episodes", "2", check=True)
    row = next(line for line in done.stdout.splitlines() if line.startswith(f"| {arm} |"))
    seeds, gap_corr, mu_corr, gap_top, mu_top = (cell.strip() for cell in row.strip("|").split("|")[1:])
    assert seeds == "5"
    assert float(mu_corr.split()[0]) > 0.8 and float(mu_top.split()[0]) > 0.8
    assert float(gap_top.split()[0]) < float(mu_top.split()[0]) - 0.3
