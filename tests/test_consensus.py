"""Best of K by consensus: of K candidates, the one whose contact centre is the medoid of the
candidates' centres is kept, for any condition.

The medoid is checked against a brute-force reading of its definition; the choice on decoded images
against a stand-in tokenizer whose codes place a contact where the test says; the assembly through a
tiny trained run against the candidates drawn one by one and their contact centres measured by the
evaluation's own function."""

import json

import pytest
import torch

from vqtouch.core import ConfigError, load_plugins
from vqtouch.plugins.cli.app import main
from vqtouch.plugins.evaluation.contact import contact_centroids, dataset_background
from vqtouch.plugins.generator import load_pipeline
from vqtouch.plugins.generator.best_of import candidate_seed, check_best_of, rank_name, sample_best_of
from vqtouch.plugins.generator.consensus import ContactConsensus, medoid_indices

from cli_checks import one_error_line

HOST = load_plugins(autoload=False)


def _brute_force_medoid(points_K2: list[tuple[float, float]]) -> int:
    totals = [
        sum(((x - u) ** 2 + (y - v) ** 2) ** 0.5 for u, v in points_K2) for x, y in points_K2
    ]  # fmt: skip
    return totals.index(min(totals))


def test_the_medoid_matches_its_definition_read_by_brute_force():
    draws = torch.Generator().manual_seed(0)
    points_BK2 = torch.rand(200, 7, 2, generator=draws, dtype=torch.float64) * 64
    chosen = medoid_indices(torch.cdist(points_BK2, points_BK2))
    assert chosen.tolist() == [_brute_force_medoid(row.tolist()) for row in points_BK2]


def test_the_medoid_ignores_an_outlier_and_ties_keep_the_earliest():
    line_K2 = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [100.0, 0.0]]], dtype=torch.float64)
    assert medoid_indices(torch.cdist(line_K2, line_K2)).tolist() == [1]
    # Two points: both have the same summed distance; a single point is its own medoid.
    pair_K2 = torch.tensor([[[3.0, 4.0], [0.0, 0.0]]], dtype=torch.float64)
    assert medoid_indices(torch.cdist(pair_K2, pair_K2)).tolist() == [0]
    same = torch.zeros(2, 4, 2, dtype=torch.float64)
    assert medoid_indices(torch.cdist(same, same)).tolist() == [0, 0]
    one = torch.ones(3, 1, 2, dtype=torch.float64)
    assert medoid_indices(torch.cdist(one, one)).tolist() == [0, 0, 0]


class _BlobTokenizer:
    """Decodes a (1, 4, 4) code grid to a 32 x 32 image: grey, with a bright 6 x 6 blob at every cell
    whose code is 1 (at that cell's place), so the test says where each candidate's contact lies."""

    def decode_codes(self, codes_BHW: torch.Tensor) -> torch.Tensor:
        images = torch.full((len(codes_BHW), 3, 32, 32), 0.5)
        for b, grid in enumerate(codes_BHW):
            for row, col in (grid == 1).nonzero().tolist():
                images[b, :, row * 8 + 1 : row * 8 + 7, col * 8 + 1 : col * 8 + 7] = 0.9
        return images


def _grid(*cells: tuple[int, int]) -> torch.Tensor:
    grid = torch.zeros(4, 4, dtype=torch.long)
    for row, col in cells:
        grid[row, col] = 1
    return grid


def test_the_candidate_where_the_others_put_the_contact_is_kept_whatever_its_batch():
    consensus = ContactConsensus(_BlobTokenizer(), torch.full((3, 32, 32), 0.5))
    # Row 0: contacts at (0,0), (0,1), (3,3) and (0,0)+(0,1): the last lies between the first two and
    # nearest all three.  Row 1: (2,2) lies between (3,3) and (2,3); (0,0) is far off at the top left.
    candidates_KBHW = torch.stack(
        [
            torch.stack([_grid((0, 0)), _grid((2, 2))]),
            torch.stack([_grid((0, 1)), _grid((3, 3))]),
            torch.stack([_grid((3, 3)), _grid((0, 0))]),
            torch.stack([_grid((0, 0), (0, 1)), _grid((2, 3))]),
        ]
    )
    assert consensus.choose(candidates_KBHW).tolist() == [3, 0]
    # A row's choice does not depend on the rows beside it.
    assert consensus.choose(candidates_KBHW[:, 1:]).tolist() == [0]
    assert consensus.choose(candidates_KBHW[:, :1]).tolist() == [3]
    centres = consensus.centres(torch.stack([_grid((0, 0)), _grid((3, 3))]))
    assert torch.allclose(centres, torch.tensor([[3.5, 3.5], [27.5, 27.5]]))


def test_bad_inputs_get_one_line_errors():
    with pytest.raises(ValueError, match=r"no-contact image must be \(3, H, W\)"):
        ContactConsensus(_BlobTokenizer(), torch.zeros(32, 32))
    consensus = ContactConsensus(_BlobTokenizer(), torch.zeros(3, 16, 16))
    with pytest.raises(ValueError, match=r"expected candidates \(K >= 1, B, H, W\)"):
        consensus.choose(torch.zeros(2, 4, 4, dtype=torch.long))
    with pytest.raises(ValueError, match=r"no-contact image is \(16, 16\) pixels, the decoded candidates \(32, 32\)"):
        consensus.centres(torch.stack([_grid((0, 0))]))


def test_consensus_ranks_a_conditioner_without_classes_and_a_class_ranking_does_not():
    without_classes = object()  # stands for an image's or a text's conditioner: no num_classes
    consensus, judge = HOST.build("best_of_ranker", "consensus"), HOST.build("best_of_ranker", "judge")
    assert check_best_of(4, without_classes, "1:visual", consensus) == 4
    with pytest.raises(ConfigError, match="--best-of-rank judge: conditioner 1:visual has no finite set of classes"):
        check_best_of(4, without_classes, "1:visual", judge)
    with pytest.raises(ConfigError, match="1:visual has no finite set of classes.*--best-of-rank consensus"):
        check_best_of(4, without_classes, "1:visual")  # the default ranker, the judge
    assert rank_name(None) == "posterior"
    assert [rank_name(consensus), rank_name(judge)] == ["consensus", "judge"]


@pytest.fixture(scope="module")
def pipe(tiny_label_run):
    return load_pipeline(tiny_label_run, host=HOST)


def test_the_pipeline_keeps_the_medoid_of_its_candidates_as_measured_one_by_one(pipe):
    ranker = pipe.best_of_ranking("consensus")
    consensus = ranker.consensus
    assert pipe.best_of_ranking("consensus") is ranker and ranker.consensus is consensus
    from vqtouch.core import Assembly
    from vqtouch.plugins.utils.splits import experiment_split

    dataset = Assembly(pipe.config, HOST).component("data.dataset")
    train, _ = experiment_split(dataset, pipe.config.data, pipe.config.seed)
    background_3HW, _ = dataset_background(train, (32, 32))
    assert torch.equal(consensus.background_3HW, background_3HW)

    generator, conditioner = pipe.generator, pipe.conditioners[0]
    labels = torch.tensor([0, 1, 2])
    condition, null = conditioner(labels), conditioner.null(3)

    def draw(generators):
        return generator.sample(condition, pipe.sampler, steps=3, null=null, guidance=1.0, generators=generators)

    row_seeds, best_of = [11, 12, 13], 5
    kept = sample_best_of(generator, conditioner, None, row_seeds, best_of, draw, pipe.device, rank=ranker)
    for row, seed in enumerate(row_seeds):
        candidates = []
        for k in range(best_of):
            generators = [torch.Generator().manual_seed(candidate_seed(s, k)) for s in row_seeds]
            candidates.append(draw(generators)[row])
        images = [pipe.tokenizer.decode_codes(grid[None]).clamp(0, 1) for grid in candidates]
        centres = [contact_centroids(image, background_3HW[None])[0].tolist() for image in images]
        assert torch.equal(kept[row], candidates[_brute_force_medoid(centres)])


def test_the_commands_take_the_consensus_and_say_so(tiny_label_run, tmp_path, capsys):
    run = tiny_label_run
    out = tmp_path / "gen"
    assert main(["generate", "--run", str(run), "--label", "1", "--n", "2", "--steps", "3", "--best-of", "3",
                 "--best-of-rank", "consensus", "--out", str(out)]) == 0  # fmt: skip
    assert json.loads((out / "generate.json").read_text())["best_of_rank"] == "consensus"
    scored = tmp_path / "scored"
    assert main(["evaluate", "generation", "--run", str(run), "--n", "3", "--steps", "3", "--best-of", "2",
                 "--best-of-rank", "consensus", "--out", str(scored)]) == 0  # fmt: skip
    scores = json.loads((scored / "generation.json").read_text())["by_conditioner"]["0:label"]
    assert scores["best_of"] == 2 and scores["best_of_rank"] == "consensus"
    capsys.readouterr()
    never = tmp_path / "never"
    assert main(["generate", "--run", str(run), "--label", "1", "--best-of-rank", "medoid", "--out", str(never)]) == 2
    assert "medoid" in one_error_line(capsys) and not never.exists()
