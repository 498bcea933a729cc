"""The sites kind's record of the tracks made landmarks answers as a set would."""

import pickle

import numpy as np

from pancam_graph.kinds.sites import TrackIds


def test_track_ids_answer_as_a_set(monkeypatch):
    monkeypatch.setattr(TrackIds, "MERGE_AT", 50)  # several merges into the sorted array
    rng = np.random.default_rng(7)
    ids, reference = TrackIds(), set()
    for track in rng.choice(10**9, 400, replace=False).tolist():
        ids.add(track)
        reference.add(track)
    ids = pickle.loads(pickle.dumps(ids))  # a checkpoint holds it
    assert len(ids) == 400 and ids.as_set() == reference
    asked = set(rng.choice(10**9, 300).tolist()) | set(list(reference)[::3])
    assert sorted(ids.not_in(asked)) == sorted(asked - reference)
    assert all((t in ids) == (t in reference) for t in asked)
    assert ids.not_in(set()) == [] and TrackIds().not_in({1, 2}) in ([1, 2], [2, 1])
