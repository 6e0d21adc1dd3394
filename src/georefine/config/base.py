"""What every configuration model shares: unknown keys are errors, vectors are 3-tuples."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

__all__ = ["StrictModel", "Vector3"]

Vector3 = tuple[float, float, float]


class StrictModel(BaseModel):
    """Base of all configuration models: unknown keys are errors, values are validated on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)
