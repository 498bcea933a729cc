"""The base of every configuration section: a frozen pydantic model that refuses unknown keys
and non-finite numbers. Measurement kinds define their own sections on it (kinds/base.py)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
