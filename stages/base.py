"""Shared base for stage parameter models."""

from pydantic import BaseModel, ConfigDict


class StageParams(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
