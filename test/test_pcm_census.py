"""The census of others in view (pcm/census.py): how old a count may be before it is not known."""

import numpy as np

from vmocap_core.pcm.census import STALE_S, Census
from vmocap_core.pcm.synthetic import benchmark_rig

S = 1_000_000_000


def test_a_count_is_known_while_every_camera_was_looked_at_lately():
    """Initialization counts every camera; then one camera per look, in turn. A count older
    than STALE_S at any camera (census off, a camera without frames) is not known (-1), so the
    path gate keeps guarding against another body."""
    rig = benchmark_rig()
    C = len(rig)
    looked: list[int] = []

    def find(images):
        looked.append(len(images))
        return [[]]  # nobody at all in the camera looked at

    census = Census(rig, every=1, find=find)
    assert census.count(0) == -1  # no look yet
    census.found(np.array([1, 2, 0, 1][:C]), stamp_ns=10 * S)
    assert census.count(10 * S) == 2 and census.count(int((10 + STALE_S) * S)) == 2
    assert census.count(int((10 + STALE_S + 0.1) * S)) == -1
    images = [np.zeros((4, 4, 3), np.uint8)] * C
    images[1] = None  # camera 1 has no frame: never looked at again
    for k in range(1, 2 * C):
        census.offer(images, np.array([0.0, 0.0, 0.9]), stamp_ns=(10 + k) * S)
    # camera 1, not looked at again, keeps its 2; the others, looked at twice or more, see nobody
    assert census.others.tolist() == [0, 2, 0, 0][:C] and census.count(13 * S) == 2
    assert census.count(int((10 + STALE_S + 1) * S)) == -1  # camera 1's look is stale
    off = Census(rig, every=0, find=find)
    off.found(np.zeros(C, int), stamp_ns=0)
    off.offer(images, np.zeros(3), stamp_ns=int(STALE_S * S) + 1)
    assert off.count(int(STALE_S * S) + 1) == -1 and len(looked) == 2 * C - 1  # the census off looked at nothing


def test_offline_runs_look_as_often_as_the_graph():
    """`vmocap process` and the benchmarks' in-process pipeline count others in view as
    often as vmocap_pcm's default, so the path gate decides alike offline and live."""
    from vmocap_core.graph_config import NODE_PARAMS
    from vmocap_core.pcm.census import EVERY

    default = next(p.default for p in NODE_PARAMS["vmocap_pcm"] if p.name == "census_every")
    assert default == EVERY
