"""Views whose CNN drew the body's sides swapped (method/mirror.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vmocap_core.apps.bench.accuracy import default_motions, prepare
from vmocap_core.keypoints import INDEX, MIRROR
from vmocap_core.method.config import PipelineConfig
from vmocap_core.method.markers import MarkerStage
from vmocap_core.method.mirror import GROUP_MASK, swapped_groups
from vmocap_core.pcm.synthetic import NoiseModel, SyntheticPcmSource, benchmark_rig

ARMS = GROUP_MASK[0]


@pytest.fixture(scope="module")
def scene():
    m = prepare(next(f for f in default_motions() if f.stem == "punch"))
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    body = m.positions[40]
    clean = NoiseModel(offset_px=0.0, amplitude=(1.0, 1.0), p_missing=0.0, p_false=0.0, p_swap=0.0)
    return rig, body, SyntheticPcmSource(rig, body[None], m.present, noise=clean)


def arms_mirrored(pcm, cameras):
    """The maps with the arms' left and right channels exchanged in the views of `cameras`."""
    src = np.arange(pcm.keypoints.size)
    chan = {int(k): i for i, k in enumerate(pcm.keypoints)}
    for i, k in enumerate(pcm.keypoints):
        if ARMS[k]:
            src[i] = chan[int(MIRROR[k])]
    maps = pcm.maps.copy()
    views = np.isin(pcm.camera, cameras)
    maps[views] = pcm.maps[views][:, src]
    return dataclasses.replace(pcm, maps=maps)


def markers_of(rig, body, pcm, **markers):
    stage = MarkerStage(rig, dataclasses.replace(PipelineConfig.of(fps=60.0).markers, **markers))
    stage.feedback(body)
    return stage.step(pcm)


def test_views_drawn_mirrored_are_read_the_other_way_round(scene):
    """Two cameras of four draw the arms mirrored (a crouched or turned body): read as drawn,
    the wrists' lattice optima lose those views' share of eq. 1; read swapped, they keep it."""
    rig, body, src = scene
    pcm = src.render(0)
    assert len(rig) == 4
    mirrored = arms_mirrored(pcm, [0, 2])
    swap = swapped_groups(rig, mirrored, body, ratio=1.5, min_value=0.5)
    assert swap[np.isin(mirrored.camera, [0, 2]), 0].all() and not swap[:, 1:].any()
    assert not swap[~np.isin(mirrored.camera, [0, 2])].any()
    wrists = [INDEX["left_wrist"], INDEX["right_wrist"]]
    clean = markers_of(rig, body, pcm)
    fixed = markers_of(rig, body, mirrored)
    as_drawn = markers_of(rig, body, mirrored, unmirror_ratio=0.0)
    np.testing.assert_allclose(fixed.weights[wrists], clean.weights[wrists], rtol=0.05)
    assert (as_drawn.weights[wrists] < 0.75 * clean.weights[wrists]).all()
    assert np.linalg.norm(fixed.positions[wrists] - body[wrists], axis=1).max() < 0.03
    assert fixed.mirrored == 0b101 and clean.mirrored == 0 and as_drawn.mirrored == 0  # cam0 and cam2, for the diagnostics


def test_a_prediction_most_views_read_mirrored_is_not_forced_on_them(scene):
    """Three cameras of four read the arms the other way round: it is the tracked body that
    swapped its sides, and the maps as drawn are what brings it back."""
    rig, body, src = scene
    mirrored = arms_mirrored(src.render(0), [0, 1, 2])
    assert not swapped_groups(rig, mirrored, body, ratio=1.5, min_value=0.5).any()
    one = arms_mirrored(src.render(0), [1])
    assert swapped_groups(rig, one, body, ratio=1.5, min_value=0.5)[:, 0].any()


def test_several_people_read_the_maps_as_drawn(scene):
    """With others in the room (max_people > 1, or Shelf's several people), maps are not read
    mirrored: at hug distance the other body's limbs lie where this one's mirrored limbs would."""
    from vmocap_core.method.people_stages import MarkerSlot

    rig, body, src = scene
    pcm = dataclasses.replace(arms_mirrored(src.render(0), [0, 2]), person=0)
    for reacquire in (False, True):  # maps from the CNN; from the person's own detections
        slot = MarkerSlot(rig, PipelineConfig.of(fps=60.0).markers, reacquire=reacquire)
        slot.step(pcm)  # a new person: their stage starts
        assert slot.stage is not None
        slot.stage.feedback(body)
        assert slot.step(pcm).mirrored == 0
