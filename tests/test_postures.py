"""The posture vocabulary: one tuple that the wire, the files, the synthetic people and the estimator share."""

from __future__ import annotations

import typing

from common import messages
from evaluation import io
from common.postures import BODY_POSTURES, POSTURES, UNKNOWN
from synth.behaviour import BENDING, LYING, SITTING, STANDING
from fusion_server import posture


def test_body_postures_are_the_postures_but_unknown_in_order() -> None:
    assert POSTURES == ("standing", "sitting", "lying", "bending", "unknown")
    assert BODY_POSTURES == ("standing", "sitting", "lying", "bending")
    assert UNKNOWN == "unknown"


def test_every_user_takes_the_one_vocabulary() -> None:
    assert messages.POSTURES is POSTURES and io.POSTURES is POSTURES
    assert typing.get_args(messages.TrackState.model_fields["posture"].annotation) == POSTURES
    assert posture.POSTURES is BODY_POSTURES


def test_synthetic_labels_index_the_body_postures() -> None:
    names = [BODY_POSTURES[k] for k in (STANDING, SITTING, LYING, BENDING)]
    assert names == ["standing", "sitting", "lying", "bending"]


def test_estimator_states_report_their_postures_by_name() -> None:
    reported = {s: posture.POSTURES[p] for s, p in zip(posture.STATES, posture.STATE_POSTURE)}
    assert reported == {
        "standing": "standing", "sitting": "sitting", "bending": "bending", "lying": "lying",
        "kneeling": "bending", "sitting_raised": "sitting", "lying_raised": "lying", "standing_raised": "standing",
        "standing_spread": "standing",
    }
