"""A demo report's results read by key convention alone (no stage in particular): the keys that
name pictures and sub-results, what was skipped and why, and values formatted for people."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

#: Result keys that describe pictures rather than score anything.
PICTURE_KEYS = frozenset({"picture", "pictures", "caption"})
#: A stage result's key for named sub-results (``{title: result}``, e.g. one per condition a generator
#: was trained with), each shown like a stage of its own: scores, verdict, pictures.
PARTS_KEY = "parts"


def format_value(value: Any) -> str:
    """A score for people: floats to 4 significant digits, integers with thousands separators."""
    if isinstance(value, bool) or value is None:
        return "-" if value is None else str(value).lower()
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    if isinstance(value, (list, tuple)):
        return ", ".join(format_value(item) for item in value)
    return str(value)


def format_duration(seconds: float) -> str:
    """``0.4 s``, ``46 s``, ``3 min 05 s`` or ``2 h 03 min``."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    whole = round(seconds)
    if whole < 60:
        return f"{whole} s"
    minutes, rest = divmod(whole, 60)
    if minutes < 60:
        return f"{minutes} min {rest:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


def is_skip_reason(value: Any) -> bool:
    """Whether ``value`` is a reason string of the form ``"skipped: ..."``."""
    return isinstance(value, str) and value.lower().startswith("skipped:")


def is_skip_key(key: str) -> bool:
    """Whether a result key holds what was skipped (``skipped`` or ``<what>_skipped``)."""
    return key == "skipped" or key.endswith("_skipped")


def skipped_items(report: Mapping[str, Any]) -> list[tuple[str, str, str]]:
    """Everything ``report`` says was skipped, as (where, what, reason).

    Found wherever it is reported: a ``"skipped"`` entry (``{name: reason}``, a list of reasons or
    one reason), a ``<what>_skipped`` entry holding a reason, or a string ``"skipped: <reason>"``;
    ``where`` is the stage or component it belongs to.
    """
    items: list[tuple[str, str, str]] = []
    for entry in report.get("stages", []):
        _collect_skipped(entry.get("result") or {}, f"stage {entry.get('stage', '?')}", (), items)
    for component in report.get("components", []):
        what = {key: value for key, value in component.items() if key != "slot"}
        _collect_skipped(what, f"component {component.get('slot', '?')}", (), items)
    rest = {key: value for key, value in report.items() if key not in ("stages", "components")}
    _collect_skipped(rest, "demo", (), items)
    return items


def _collect_skipped(value: Any, where: str, path: tuple[str, ...], items: list[tuple[str, str, str]]) -> None:
    if isinstance(value, Mapping):
        for key, item in value.items():
            if key == "skipped":
                _collect_reasons(item, where, path, items)
            elif key.endswith("_skipped"):
                _collect_reasons(item, where, (*path, key[: -len("_skipped")]), items)
            else:
                _collect_skipped(item, where, (*path, str(key)), items)
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            _collect_skipped(item, where, (*path, str(index)), items)
    elif is_skip_reason(value):
        items.append((where, _path_text(path), value.split(":", 1)[1].strip()))


def _collect_reasons(value: Any, where: str, path: tuple[str, ...], items: list[tuple[str, str, str]]) -> None:
    if isinstance(value, Mapping):
        for name, reason in value.items():
            items.append((where, _path_text((*path, str(name))), _reason_text(reason)))
    elif isinstance(value, (list, tuple)):
        for reason in value:
            items.append((where, _path_text(path), _reason_text(reason)))
    elif isinstance(value, str) and value:  # a count or a flag is not a reason; None means nothing was skipped
        items.append((where, _path_text(path), _reason_text(value)))


def _reason_text(reason: Any) -> str:
    text = reason if isinstance(reason, str) else json.dumps(reason, default=str)
    return text.split(":", 1)[1].strip() if is_skip_reason(text) else text


def _path_text(path: tuple[str, ...]) -> str:
    # A component's own status names the component itself, which `where` already says.
    return " / ".join(part for part in path if part != "status") or "-"


def stage_parts(result: Mapping[str, Any]) -> dict[str, Mapping[str, Any]]:
    """A stage result's named sub-results (:data:`PARTS_KEY`), those that are results (mappings)."""
    parts = result.get(PARTS_KEY)
    if not isinstance(parts, Mapping):
        return {}
    return {str(title): part for title, part in parts.items() if isinstance(part, Mapping)}


def skipped_groups(skipped: list[tuple[str, str, str]]) -> dict[tuple[str, str], list[str]]:
    """``(what, reason) -> [where, ...]``: one entry per thing skipped for one reason (a metric missing
    its weights is skipped by every stage that scores), in the order first met."""
    grouped: dict[tuple[str, str], list[str]] = {}
    for where, what, reason in skipped:
        reason = reason.strip()
        name = what.split(" / ")[-1]
        if name == "-":  # a component's own skip: the same reason as the stages' skips of it
            name = next((known for known, said in grouped if said == reason), "-")
        places = grouped.setdefault((name, reason), [])
        if where not in places:
            places.append(where)
    return grouped


def component_status(component: Mapping[str, Any]) -> str:
    """A component's status for the reports' tables: a skip's reason stays in the Skipped section."""
    status = str(component.get("status", "-"))
    return "skipped (reason under Skipped)" if is_skip_reason(status) else status
