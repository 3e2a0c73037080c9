"""The project's data splits: which simulated sequences serve which purpose.

Sequences are the unit of splitting (consecutive frames are nearly identical). Every split
is a ``lidar-sim generate`` seed: sequence ``s`` of a split has scene and noise seed
``seed * 1000 + s``, so splits with different seeds never share a sequence. The reference
perception models learn on ``reference_train``; the meta models are fitted on
``meta_train`` and evaluated on ``meta_test``; ``demo`` is the default demo input.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Split:
    """A named set of simulated sequences."""

    name: str
    seed: int
    sequences: int
    frames: int

    def sequence_seed(self, s: int) -> int:
        """Scene / noise seed of sequence ``s`` (same rule as ``lidar-sim generate``)."""
        if not 0 <= s < self.sequences:
            raise IndexError(f"split {self.name!r} has {self.sequences} sequences, not {s + 1}")
        return self.seed * 1000 + s


SPLITS: dict[str, Split] = {s.name: s for s in (
    Split("reference_train", seed=101, sequences=12, frames=30),
    Split("reference_test", seed=102, sequences=4, frames=30),
    Split("meta_train", seed=201, sequences=12, frames=40),
    Split("meta_test", seed=301, sequences=6, frames=40),
    Split("demo", seed=7, sequences=1, frames=100),
)}


def split(name: str) -> Split:
    """The split called ``name`` (KeyError listing the known names otherwise)."""
    try:
        return SPLITS[name]
    except KeyError:
        raise KeyError(f"unknown split {name!r}; known: {sorted(SPLITS)}") from None
