"""Utilities the stages and commands share: images, data splits, progress bars, thread policy,
local weights files and frozen modules, JSON files checked by pydantic models."""
