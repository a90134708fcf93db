"""Small configurations the test modules share at import (a fixture cannot serve a module's
parametrization)."""

from __future__ import annotations

SMALL_ENTITY = {
    "network": "entity",
    "swarm_value": False,
    "entity_nearest": 0,
    "poi_order": "nearest",
    "entity_dim": 8,
    "entity_heads": 2,
    "entity_layers": 1,
}
"""The anysize preset's options for attention over every entity, shrunk: every entity of each
type (no nearest-K view), one small attention layer of 2 heads."""
