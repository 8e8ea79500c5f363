"""A seeded fuzz run (benchmarks/fuzz.py): mutated recordings through `read_log`, the
byte-stream reader and `physfuse inspect` raise only physfuse's errors, and every changed
value is flagged."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("fuzz", ROOT / "benchmarks" / "fuzz.py")
assert _spec is not None and _spec.loader is not None
fuzz = importlib.util.module_from_spec(_spec)
sys.modules["fuzz"] = fuzz
_spec.loader.exec_module(fuzz)


def test_mutated_recordings_raise_only_physfuse_errors_and_flag_every_change():
    result = fuzz.run_inputs(seed=2026, n=300, seconds=0.1)
    outcomes = {}
    for _mutation, _reader, outcome, n in result["counts"]:
        outcomes[outcome] = outcomes.get(outcome, 0) + n
    assert sum(outcomes.values()) == 300 * len(fuzz.READERS)
    assert outcomes.get("flagged", 0) > 0 and outcomes.get("exact", 0) > 0  # damage was done
    assert result["failures"] == {}, result["examples"]


def test_every_mutation_changes_the_bytes():
    import numpy as np

    rng = np.random.default_rng(0)
    original = fuzz.originals(0.05)[0]
    for name, mutate in fuzz.MUTATIONS.items():
        assert any(mutate(rng, original) != original.data for _ in range(5)), name
