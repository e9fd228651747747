"""The independent evaluation of a run's final policy plays initial states the run never saw."""

from dvla.config import EvalConfig

from benchmarks.final_eval import fresh_seed


def test_fresh_episodes_meet_neither_the_runs_evaluations_nor_its_training_envs():
    episodes = 128
    for seed in range(1, 100):
        fresh = range(fresh_seed(seed), fresh_seed(seed) + episodes)
        first = EvalConfig().first_seed(seed)
        evals = range(first, first + 1024)
        # rollout r's envs: (seed * 1000 + r) * 10,000 + group * 1000 + env + episodes played
        training = range(seed * 1000 * 10_000, (seed * 1000 + 100) * 10_000)
        for other in (evals, training):
            assert fresh.stop <= other.start or other.stop <= fresh.start, (seed, fresh, other)
