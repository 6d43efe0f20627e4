"""Best of K's rankers are plugins: a third-party ranker is one registration, and the pipeline and the
commands use it by name; an unknown name is refused in one line naming the registered rankers; one
candidate is plain sampling whatever the ranker."""

import json
import sys
from typing import Literal

import pytest
import torch

from vqtouch.core import BestOfRanker, ConfigError, PluginConfig, hookimpl, load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.generator import load_pipeline
from vqtouch.plugins.testing import check_plugin

from cli_checks import one_error_line

BUILT_IN = ["consensus", "judge", "posterior"]


class LastConfig(PluginConfig):
    """Options of the ``last`` ranker (none besides its name)."""

    name: Literal["last"] = "last"


class LastRanker(BestOfRanker):
    """Keeps every row's last candidate, and records what it was given."""

    def __init__(self) -> None:
        self.pipelines: list = []
        self.candidates: list[torch.Tensor] = []

    def prepare(self, pipeline) -> None:
        self.pipelines.append(pipeline)

    def choose(self, candidates_KBHW, batch):
        self.candidates.append(candidates_KBHW.clone())
        return torch.full((candidates_KBHW.shape[1],), len(candidates_KBHW) - 1, dtype=torch.long)


@hookimpl
def vqtouch_register_best_of_rankers(register):
    register("last", lambda config, context: LastRanker(), LastConfig, description="Every row's last candidate.")


@pytest.fixture(scope="module")
def plugin():
    import types

    module = types.ModuleType("last_ranker_plugin")
    module.vqtouch_register_best_of_rankers = vqtouch_register_best_of_rankers
    return module


@pytest.fixture(scope="module")
def pipe(tiny_label_run, plugin):
    return load_pipeline(tiny_label_run, host=load_plugins(autoload=False, extra=[plugin]))


def test_the_built_in_rankers_are_registered():
    assert load_plugins(autoload=False).registry("best_of_ranker").names() == BUILT_IN


def test_a_plugin_ranker_is_one_registration_and_the_pipeline_keeps_its_choice(pipe):
    check_plugin(pipe.host, "best_of_ranker", "last")
    images = pipe(label=[0, 1, 2], steps=3, seed=4, best_of=3, best_of_rank="last")
    ranker = pipe.best_of_ranking("last")
    assert ranker.pipelines == [pipe]  # prepared once, with the pipeline that ranks
    (candidates_KBHW,) = ranker.candidates
    assert candidates_KBHW.shape[:2] == (3, 3) and not torch.equal(candidates_KBHW[-1], candidates_KBHW[0])
    kept = torch.cat([pipe.tokenizer.decode_codes(grid[None]).cpu() for grid in candidates_KBHW[-1]])
    assert torch.equal(images, kept)


def test_one_candidate_is_plain_sampling_and_ranks_nothing(pipe):
    ranker = pipe.best_of_ranker("last")
    seen = len(ranker.candidates)
    plain = pipe(label=[0, 1, 2], steps=3, seed=5)
    assert torch.equal(pipe(label=[0, 1, 2], steps=3, seed=5, best_of=1, best_of_rank="last"), plain)
    assert len(ranker.candidates) == seen


def test_an_unknown_ranker_is_refused_naming_the_registered_ones(pipe):
    refused = r"^--best-of-rank 'medoid': choose one of consensus, judge, last, posterior$"
    with pytest.raises(ConfigError, match=refused):
        pipe(label=[0], steps=3, best_of=2, best_of_rank="medoid")


def test_the_commands_take_a_plugin_ranker_by_name(tiny_label_run, plugin, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "last_ranker_plugin", plugin)
    generate = ["generate", "--run", str(tiny_label_run), "--label", "1", "--n", "2", "--steps", "3", "--best-of", "2"]
    never = tmp_path / "never"
    assert main([*generate, "--best-of-rank", "medoid", "--out", str(never)]) == 2
    assert one_error_line(capsys) == f"--best-of-rank 'medoid': choose one of {', '.join(BUILT_IN)}"
    monkeypatch.setenv("VQTOUCH_PLUGINS", "last_ranker_plugin")
    assert main([*generate, "--best-of-rank", "medoid", "--out", str(never)]) == 2
    assert one_error_line(capsys) == "--best-of-rank 'medoid': choose one of consensus, judge, last, posterior"
    assert not never.exists()
    out = tmp_path / "gen"
    assert main([*generate, "--best-of-rank", "last", "--out", str(out)]) == 0
    assert json.loads((out / "generate.json").read_text())["best_of_rank"] == "last"


class _Silent(BestOfRanker):
    """Implements neither score nor choose."""


def test_the_contract_check_refuses_a_ranker_that_ranks_nothing(make_plugin):
    @hookimpl
    def vqtouch_register_best_of_rankers(register):
        register("last", lambda config, context: _Silent(), LastConfig, description="Ranks nothing.")

    host = load_plugins(autoload=False, extra=[make_plugin("silent_ranker", vqtouch_register_best_of_rankers)])
    with pytest.raises(AssertionError, match="best_of_ranker 'last': implements neither score"):
        check_plugin(host, "best_of_ranker", "last")
