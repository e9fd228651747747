"""`dvla bench learn-vla`'s options reach the recipe: left out, the clone keeps the recipe's
defaults (benchmarks.learn_vla.CLONE_EPOCHS, NOISE_STD); given, they replace them; bad values are
refused with one line before anything runs. run_bench is replaced: this is the option parsing."""

import pytest
from typer.testing import CliRunner

import benchmarks.learn_vla as learn_vla
from dvla.orchestrator.cli import app


@pytest.fixture
def recipes(monkeypatch):
    seen = []

    def run_bench(recipe, *args, **kwargs):
        seen.append(recipe)
        raise SystemExit(0)

    monkeypatch.setattr(learn_vla, "run_bench", run_bench)
    return seen


def invoke(tmp_path, *args):
    return CliRunner().invoke(app, ["bench", "learn-vla", "--json", str(tmp_path / "out.json"), *args])


def test_left_out_clone_options_keep_the_recipe_defaults(tmp_path, recipes):
    assert invoke(tmp_path).exit_code == 0
    assert recipes[-1].clone_epochs == learn_vla.CLONE_EPOCHS == 4
    assert recipes[-1].clone_noise_std == learn_vla.NOISE_STD


def test_given_clone_options_replace_them(tmp_path, recipes):
    assert invoke(tmp_path, "--clone-epochs", "20", "--clone-noise-std", "0.59").exit_code == 0
    assert (recipes[-1].clone_epochs, recipes[-1].clone_noise_std) == (20, 0.59)


@pytest.mark.parametrize("args, word", [(["--clone-epochs", "0"], "--clone-epochs"),
                                        (["--clone-noise-std", "0"], "--clone-noise-std")])
def test_bad_clone_options_are_refused(tmp_path, recipes, args, word):
    res = invoke(tmp_path, *args)
    assert res.exit_code != 0 and word in res.output and not recipes
