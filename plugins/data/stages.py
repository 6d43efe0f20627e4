"""The ``render`` stage: the experiment's data, written to a browsable folder inside the run.

For procedural scenes this is rendering by the experiment's sensor; for a reader of real data
it is a copy of the first samples, which shows what the models will see (after resizing).
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from vqtouch.core import Section, StageJob, hookimpl


class RenderSection(Section):
    """Options of the ``render`` stage."""

    num_samples: int = Field(
        64, ge=1, le=1_000_000, description="How many of the dataset's first samples to write (fewer if it is smaller)."
    )
    batch_size: int = Field(32, ge=1, le=4096, description="Samples rendered per step.")
    folder: str = Field(
        "data",
        min_length=1,
        pattern=r"^[A-Za-z0-9._-]+$",
        description="Folder inside the run directory that receives the samples.",
    )


def run_render_stage(job: StageJob) -> dict[str, Any]:
    """Write the first ``render.num_samples`` samples of ``data.dataset`` to ``<run>/<render.folder>``."""
    from .export import export_samples  # imports torch: only when the stage runs

    section: RenderSection = job.section
    dataset = job.assembly.component("data.dataset")
    out = job.run.path / section.folder
    record = export_samples(dataset, range(min(section.num_samples, len(dataset))), out, batch_size=section.batch_size)
    job.run.write_json(f"{section.folder}/render.json", record)
    return {
        "samples": record["samples"],
        "samples_per_second": record["images_per_second"],
        "folder": section.folder,
        "picture": f"{section.folder}/preview.png",
        "caption": "The first samples, each as its tactile image followed by its visual image (the tactile "
        "image again when there is none), four pairs per row.",
    }


@hookimpl
def vqtouch_register_stages(register):
    register(
        "render",
        run_render_stage,
        section=RenderSection,
        needs=("data.dataset",),
        uses=("sensor",),
        demo={"num_samples": 32},
        description="Write the experiment's data (procedural scenes rendered by its sensor) to a browsable "
        "folder in the run.",
    )
