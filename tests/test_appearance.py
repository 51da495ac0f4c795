"""Colour descriptors: the bins, the distance, and what a camera measures inside a person's boxes."""

from __future__ import annotations

import numpy as np
import pytest

from camera_worker.looks import LookAnswerer, describe
from common import appearance
from common.appearance import N_BINS, colour_bins, describe_people, hellinger, quantise
from common.messages import LookRequest, PersonRegion

GREY0 = 2 * appearance.HUE_BINS  # first grey bin (black)


def test_bins_of_known_colours_worked_by_hand():
    px = np.array([
        [0, 0, 255],      # pure red: hue 0, strong -> bin 0 * 2 + 1
        [255, 0, 0],      # pure blue: OpenCV hue 120 -> sector 8, strong -> 17
        [128, 128, 128],  # mid grey: value 128 -> third grey bin
        [10, 10, 10],     # black
        [240, 240, 240],  # light grey
        [90, 110, 130],   # faint warm tint, saturation 78: moderate, hue 15 -> sector 1 -> 2
    ], dtype=np.uint8)
    assert colour_bins(px).tolist() == [1, 17, GREY0 + 2, GREY0, GREY0 + 3, 2]


def test_bins_ignore_a_change_of_illumination_of_a_coloured_cloth():
    shirt = np.array([[40, 60, 200], [200, 90, 30], [60, 170, 60]], dtype=np.uint8)
    for gain in (0.55, 0.8, 1.2):
        lit = np.clip(np.rint(shirt * gain), 0, 255).astype(np.uint8)
        assert colour_bins(lit).tolist() == colour_bins(shirt).tolist()


def test_quantised_histogram_sums_to_about_255_and_hellinger_bounds():
    h = np.zeros(N_BINS)
    h[[1, 5]] = (30, 10)
    q = np.frombuffer(quantise(h), np.uint8)
    assert len(q) == N_BINS and q[1] == 191 and q[5] == 64  # 255 * 3/4 and 255 / 4, rounded
    assert quantise(np.zeros(N_BINS)) == bytes(N_BINS)
    assert hellinger(h, 2 * h) == pytest.approx(0.0, abs=1e-9)
    other = np.zeros(N_BINS)
    other[7] = 1
    assert hellinger(h, other) == pytest.approx(1.0)
    assert hellinger(h, np.zeros(N_BINS)) == 1.0


def test_describe_counts_only_foreground_and_leaves_out_what_a_nearer_person_hides():
    image = np.zeros((100, 100, 3), np.uint8)
    image[:, :] = (0, 0, 255)          # red everywhere
    image[:, 50:] = (255, 0, 0)        # blue on the right half
    mask = np.zeros((100, 100), np.uint8)
    mask[20:80, 20:80] = 255           # foreground: a 60 x 60 square
    far = (5.0, [(20, 20, 80, 40), (20, 40, 80, 60), (20, 60, 80, 80)])
    near = (2.0, [(50, 0, 100, 100), (0, 0, 0, 0), (0, 0, 0, 0)])  # hides the right half of everything
    (hist_far, pix_far, vis_far), (hist_near, pix_near, _) = describe_people(image, mask, [far, near])
    # the far person keeps its left half: 30 x 20 red foreground pixels per band
    assert pix_far.tolist() == [600, 600, 600]
    assert vis_far.tolist() == pytest.approx([0.5, 0.5, 0.5])
    assert all(hist_far[k, 1] == 600 and hist_far[k].sum() == 600 for k in range(3))
    # the near person's head box covers foreground columns 50..79, rows 20..79: blue
    assert pix_near.tolist() == [30 * 60, 0, 0]
    assert hist_near[0, 17] == 30 * 60


def test_describe_reads_a_downscaled_mask_at_the_capture_resolution():
    image = np.full((100, 200, 3), (0, 200, 0), np.uint8)
    mask = np.zeros((50, 100), np.uint8)
    mask[10:20, 10:30] = 255  # capture pixels rows 20..39, columns 20..59
    (hist, pixels, visible), = describe_people(image, mask, [(3.0, [(0, 0, 200, 100)] * 3)])
    assert pixels.tolist() == [800, 800, 800] and visible.tolist() == [1.0, 1.0, 1.0]


def test_answerer_answers_once_and_not_when_the_request_is_stale():
    image = np.full((60, 80, 3), (30, 30, 220), np.uint8)
    mask = np.full((60, 80), 255, np.uint8)
    region = PersonRegion(track=4, depth_m=3.0, boxes=[(0, 0, 80, 20), (0, 20, 80, 40), (0, 40, 80, 60)])
    a = LookAnswerer()
    assert a.answer(image, mask, 0) == []
    a.ask(LookRequest(cam="c1", stamp_ns=1_000_000_000, people=[region], ttl_ms=500))
    (look,) = a.answer(image, mask, 1_100_000_000)
    assert look.track == 4 and look.pixels == [1600, 1600, 1600] and len(look.hist) == 3 * N_BINS
    assert a.answer(image, mask, 1_200_000_000) == []  # answered once
    a.ask(LookRequest(cam="c1", stamp_ns=1_000_000_000, people=[region], ttl_ms=500))
    assert a.answer(image, mask, 1_600_000_000) == [] and a.expired == 1
    assert describe([region], image[:, :, 0], mask)[0].pixels == [1600, 1600, 1600]  # grey frames work too
