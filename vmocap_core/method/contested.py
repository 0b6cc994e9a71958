"""Several people: markers two people found in one place (our extension; the paper tracks one
person).

Each person's maps come from the landmark model run on their own crop, and a crop holds the
people next to them too: side by side, the model may hang one person's foot on the neighbour's
foot in every view at once. That person's lattice search follows it, their views agree with it,
and frame set by frame set the IK draws the leg over onto the other body. Two bodies' joint
centres are not closer than about a limb's thickness, so two people's markers within `radius`
are one body part, and which of the two it belongs to the maps cannot say: neither person's IK
uses it in that frame set (people_stages.PeopleSkeletons). The rest of each body holds the
limb where it was, and the next frame set's search starts from there.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from .results import Markers


def contested(markers: Mapping[int, Markers], radius: float) -> dict[int, np.ndarray]:
    """Per person: (25,) True where one of their lattice markers lies within `radius` of another
    person's (markers of weight 0 and triangulated ones, while initializing, take no part)."""
    out = {n: np.zeros(len(m.weights), dtype=bool) for n, m in markers.items()}
    found = {n: np.where((m.weights > 0)[:, None], m.positions, np.nan)
             for n, m in markers.items() if m.kind == "lattice"}
    numbers = list(found)
    for i, a in enumerate(numbers):
        for b in numbers[i + 1:]:
            near = np.linalg.norm(found[a][:, None] - found[b][None], axis=-1) < radius  # (25, 25); NaN: False
            out[a] |= near.any(axis=1)
            out[b] |= near.any(axis=0)
    return out
