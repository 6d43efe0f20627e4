"""Running one stage of an experiment in a run: the one path the CLI, the demo and tests share."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from vqtouch.core.errors import VqtouchError
from vqtouch.core.stages import StageJob, StageRun, StageUnavailable, unavailable_reason
from vqtouch.plugins.utils.seeding import seed_everything

if TYPE_CHECKING:
    from vqtouch.core.assembly import Assembly


@dataclass
class StageOutcome:
    """What happened when a stage was asked to run: ``status`` is ``ran``, ``unavailable`` or ``failed``."""

    stage: str
    status: str
    reason: str = ""
    result: dict[str, Any] | None = None
    seconds: float = 0.0

    def describe(self) -> str:
        """One line for reports, e.g. ``ran (23 s)`` or ``cannot run: ...``."""
        if self.status == "ran":
            return f"ran ({self.seconds:.0f} s)"
        if self.status == "unavailable":
            return f"cannot run: {self.reason}"
        return f"failed: {self.reason}"


def run_stage(stage: str, assembly: Assembly, run: StageRun, *, resume: bool = False) -> StageOutcome:
    """Run one stage of ``assembly``'s experiment in ``run``: the one path the CLI, the demo and
    tests share.

    Every random number generator is seeded with the experiment's seed first, so a stage's
    result does not depend on what ran before it in the same process.  A stage that cannot
    run says why (``unavailable``); a user error while running is ``failed`` with its
    one-line message.  Other exceptions propagate.
    """
    config, host = assembly.config, assembly.host
    entry = host.stage(stage)
    reason = unavailable_reason(stage, config, host)
    if reason is not None:
        return StageOutcome(stage, "unavailable", reason)
    seed_everything(config.seed, config.deterministic)
    job = StageJob(stage, config, host, run, assembly, getattr(config, stage, None) if entry.section else None, resume)
    start = time.perf_counter()
    try:
        result = entry.load_run()(job)
    except StageUnavailable as exc:
        return StageOutcome(stage, "unavailable", str(exc), seconds=time.perf_counter() - start)
    except VqtouchError as exc:
        return StageOutcome(stage, "failed", str(exc), seconds=time.perf_counter() - start)
    return StageOutcome(stage, "ran", result=result or {}, seconds=time.perf_counter() - start)
