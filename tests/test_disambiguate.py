"""A/B labelling on hand-made centre sets with known labels, broken patterns included."""

from __future__ import annotations

import numpy as np
import pytest

from crossline.errors import StageError
from crossline.scan.labels import Disambiguator, bridge_gaps, disambiguate, nearest_in_column, reference_gap
from crossline.scan.stripes import MERGED

U = np.arange(100.0, 400.0)


def line(laser: str, frame: int, speed: float = 0.0) -> np.ndarray:
    """Row of stripe A or B at column U in a frame: an X crossing at u = 250."""
    slope = 0.3 if laser == "A" else -0.3
    return 200.0 + slope * (U - 250.0) + speed * frame


def build(states, speed=0.0, drop_frames=()):
    """Centre table of a scan: per frame the stripes its state lights; true labels too."""
    rows = {"frame": [], "u": [], "v": [], "flags": [], "truth": []}
    for f, s in enumerate(states):
        if f in drop_frames:
            continue
        lit = {"A": "A", "B": "B", "AB": "AB", "off": ""}[s]
        for laser in lit:
            rows["frame"].append(np.full(U.size, f))
            rows["u"].append(U)
            rows["v"].append(line(laser, f, speed))
            rows["flags"].append(np.zeros(U.size, np.uint8))
            rows["truth"].append(np.full(U.size, laser))
    out = {k: np.concatenate(v) if v else np.empty(0) for k, v in rows.items()}
    o = np.lexsort((out["v"], out["u"], out["frame"]))
    return {k: v[o] for k, v in out.items()}


def run(states, t, **kw):
    return disambiguate(t["frame"], t["u"], t["v"], t["flags"], np.arange(len(states)),
                        np.array(states), **kw)


def sep(t):
    """|vA - vB| at each centre's column (the crossing band is where it is small)."""
    return np.abs(0.6 * (t["u"] - 250.0))


def test_paper_pattern_labels_everything_right():
    states = ["A", "B", "AB"] * 10
    t = build(states, speed=0.4)
    label, dist, counts = run(states, t, threshold_px=10, ambiguity_px=3)
    done = label != ""
    assert np.all(label[done] == t["truth"][done])
    ab = np.isin(t["frame"], np.flatnonzero(np.array(states) == "AB"))
    # only the crossing band is dropped (ambiguous), nothing else
    assert np.all(done[ab & (sep(t) > 6)])
    assert counts["dropped"]["ambiguous"] == np.count_nonzero(ab & ~done)
    assert counts["labelled"]["A"] + counts["labelled"]["B"] == np.count_nonzero(done)
    assert counts["frames"] == {"A": 10, "B": 10, "AB": 10, "off": 0}
    assert np.all(np.isfinite(dist[ab & done])) and np.all(np.isnan(dist[~ab]))


def test_paper_rule_labels_the_crossing_band_and_mislabels_some():
    # the paper's nearest-wins (ambiguity 0) without prediction, fast motion: near the crossing
    # the stale reference of the other laser is nearer, which is a wrong label
    states = ["A", "B", "AB"] * 6
    t = build(states, speed=1.5)
    label, _, _counts = run(states, t, threshold_px=10, ambiguity_px=0, predict=False)
    ab = np.isin(t["frame"], np.flatnonzero(np.array(states) == "AB"))
    wrong = (label != "") & (label != t["truth"])
    assert wrong[ab].sum() > 0
    assert np.all(~wrong[ab & (sep(t) > 15)])  # none away from the crossing band
    # with prediction and the unique-match rule: no wrong label at all
    label2, _, counts2 = run(states, t, threshold_px=10, ambiguity_px=3, predict=True)
    assert np.all((label2 == "") | (label2 == t["truth"]))
    assert counts2["dropped"]["ambiguous"] > 0


def test_prediction_keeps_up_with_fast_motion():
    states = ["A", "B", "AB"] * 6
    t = build(states, speed=4.0)  # 8 px between the A frame and the AB frame
    ab = np.isin(t["frame"], np.flatnonzero(np.array(states) == "AB"))
    label, _, _ = run(states, t, threshold_px=5, predict=False)
    # the A reference (two frames back, 8 px away) is out of reach of the paper's rule
    assert (label[ab & (t["truth"] == "A")] == "").mean() > 0.9
    label, _, _c = run(states, t, threshold_px=5, predict=True)
    first_ab = t["frame"] == 2  # no second reference frame yet: not predicted
    done = (label != "") & ab & ~first_ab
    assert np.all(label[done] == t["truth"][done])
    assert done.sum() >= 0.9 * np.count_nonzero(ab & ~first_ab & (sep(t) > 6))


def test_missing_a_frame_is_counted_not_mislabelled():
    # frame 3 should be A but the arm sent B (pattern broken); frame 6 lost entirely
    states = ["A", "B", "AB", "B", "B", "AB", "A", "B", "AB", "A", "B", "AB"]
    t = build(states, drop_frames=())
    label, _, counts = run(states, t, max_frame_gap=3)
    # AB frame 5: its latest A is frame 0 (5 frames back): dropped whole
    assert np.all(label[t["frame"] == 5] == "")
    assert counts["AB_frames_without_reference"]["A"] == 1
    assert counts["dropped"]["no_reference"] == np.count_nonzero(t["frame"] == 5)
    done = label != ""
    assert np.all(label[done] == t["truth"][done])


def test_off_frame_in_place_of_b():
    states = ["A", "B", "AB", "A", "off", "AB", "A", "B", "AB"]
    t = build(states)
    label, _, counts = run(states, t, max_frame_gap=3)
    # AB frame 5: B reference is frame 1, 4 frames back: dropped
    assert np.all(label[t["frame"] == 5] == "")
    assert counts["AB_frames_without_reference"] == {"A": 0, "B": 1}
    assert counts["frames"]["off"] == 1
    done = label != ""
    assert np.all(label[done] == t["truth"][done])


def test_off_frame_centres_are_dropped():
    states = ["A", "B", "AB", "off"]
    t = build(states)
    extra = {"frame": np.full(3, 3), "u": np.array([150.0, 151, 152]), "v": np.full(3, 20.0),
             "flags": np.zeros(3, np.uint8), "truth": np.full(3, "")}
    t = {k: np.concatenate([t[k], extra[k]]) for k in t}
    label, _, counts = run(states, t)
    assert counts["dropped"]["off_frame"] == 3 and np.all(label[t["frame"] == 3] == "")


def test_scan_start_ab_frame_has_no_reference():
    states = ["AB", "A", "B", "AB"]
    t = build(states)
    label, _, counts = run(states, t)
    assert np.all(label[t["frame"] == 0] == "")
    assert counts["AB_frames_without_reference"] == {"A": 1, "B": 1}


def test_no_a_frame_is_an_error_naming_the_scan():
    states = ["B", "AB", "B", "AB"]
    t = build(states)
    with pytest.raises(StageError, match=r"scan gauge: has AB frames but no A frame"):
        run(states, t, scan="gauge")
    # a scan of single-laser frames only is fine
    states = ["A", "A", "A"]
    label, _, _ = run(states, build(states))
    assert np.all(label == "A")


def test_unmatched_merged_and_conflict():
    d = Disambiguator(threshold_px=10, max_frame_gap=3, ambiguity_px=3, predict=False)
    u = np.array([10.0, 10.0, 11.0, 12.0, 12.0])
    d.process(0, "A", np.array([10.0, 11.0, 12.0]), np.array([100.0, 100.0, 100.0]), np.zeros(3, np.uint8))
    d.process(1, "B", np.array([10.0, 11.0, 12.0]), np.array([150.0, 150.0, 150.0]), np.zeros(3, np.uint8))
    v = np.array([101.0, 149.0, 125.0, 100.5, 102.0])
    flags = np.array([0, MERGED, 0, 0, 0], np.uint8)
    label, dist = d.process(2, "AB", u, v, flags)
    # col 10: A matched, the B-side one is merged; col 11: 25 px from both: unmatched;
    # col 12: two centres near A: the nearer keeps the label, the other is a conflict
    assert list(label) == ["A", "", "", "A", ""]
    assert d.counts["dropped"]["merged"] == 1
    assert d.counts["dropped"]["unmatched"] == 1
    assert d.counts["dropped"]["conflict"] == 1
    np.testing.assert_allclose(dist[[0, 3]], [1.0, 0.5])


def test_stale_reference_not_used():
    d = Disambiguator(threshold_px=10, max_frame_gap=2, predict=False)
    z = np.zeros(1, np.uint8)
    d.process(0, "A", np.array([5.0]), np.array([50.0]), z)
    d.process(1, "B", np.array([5.0]), np.array([80.0]), z)
    d.process(2, "off", np.empty(0), np.empty(0), np.empty(0, np.uint8))
    label, _ = d.process(3, "AB", np.array([5.0]), np.array([50.0]), z)
    assert label[0] == "" and d.counts["AB_frames_without_reference"]["A"] == 1


def test_nearest_in_column():
    ru = np.array([1.0, 1.0, 2.0, 4.0])
    rv = np.array([10.0, 30.0, 5.0, 7.0])
    j, d = nearest_in_column(ru, rv, np.array([1.0, 1.0, 2.0, 3.0]), np.array([12.0, 26.0, 9.0, 7.0]))
    assert list(j) == [0, 1, 2, -1]
    np.testing.assert_allclose(d, [2.0, 4.0, 4.0, np.inf])


def test_frames_out_of_order_rejected():
    with pytest.raises(StageError, match="frame order"):
        disambiguate(np.array([1, 0]), np.array([1.0, 1.0]), np.array([1.0, 2.0]),
                     np.zeros(2, np.uint8), np.array([0, 1]), np.array(["A", "B"]))


@pytest.mark.parametrize(("period", "gap"), [(["A", "B", "AB"], 2), (["A", "B", "AB", "AB"], 3),
                                             (["A", "B", "AB", "AB", "AB", "AB"], 5),
                                             (["AB", "A", "B"], 2), (["A", "B"], 1), (["A", "AB"], 1)])
def test_reference_gap_of_a_pattern(period, gap):
    assert reference_gap(period) == gap


def test_more_ab_frames_per_period_labelled_with_the_pattern_gap():
    """A, B and four AB frames: the last AB frame's references are 5 and 4 frames old; with the
    gap the pattern needs every AB frame is labelled (right), with the paper's 3 two are lost."""
    states = ["A", "B", "AB", "AB", "AB", "AB"] * 6
    t = build(states, speed=0.4)
    gap = reference_gap(states[:6]) + 1
    label, _, counts = run(states, t, threshold_px=10, ambiguity_px=3, max_frame_gap=gap)
    done = label != ""
    assert np.all(label[done] == t["truth"][done])
    assert counts["AB_frames_without_reference"] == {"A": 0, "B": 0}
    ab = np.isin(t["frame"], np.flatnonzero(np.array(states) == "AB"))
    assert np.all(done[ab & (sep(t) > 6)])
    _, _, tight = run(states, t, threshold_px=10, ambiguity_px=3, max_frame_gap=3)
    assert tight["AB_frames_without_reference"]["A"] == 2 * 6


def test_bridge_gaps_fills_a_broken_stripe_not_a_jump():
    u = np.arange(100.0, 140.0)
    v = 50 + 0.7 * (u - 100)
    keep = np.ones(u.size, bool)
    keep[[5, 6, 7, 20]] = False  # gaps of three columns and of one
    u2 = np.arange(141.0, 150.0)  # another surface, 150 rows away: a jump
    bu, bv = bridge_gaps(np.r_[u[keep], u2], np.r_[v[keep], np.full(u2.size, 200.0)], 8)
    assert sorted(set(bu) - set(u[keep]) - set(u2)) == [105, 106, 107, 120]
    np.testing.assert_allclose(bv[bu < 140], 50 + 0.7 * (bu[bu < 140] - 100), atol=1e-12)
    assert np.all(np.diff(bu) >= 0)
    # max_gap counts the missing columns: a gap of three is bridged with 3, not with 2; 1 bridges one
    for max_gap, filled in ((3, [105, 106, 107, 120]), (2, [120]), (1, [120]), (0, [])):
        bu, _ = bridge_gaps(u[keep], v[keep], max_gap)
        assert sorted(set(bu) - set(u[keep])) == filled, max_gap


def test_gappy_reference_still_labels_and_two_segments_of_one_laser_both_stay():
    """A speckled reference misses columns; a step puts two segments of laser A in the same
    columns (top face and plate). Bridged references label the AB centres in the gaps, and
    both A segments keep their label (they match two different reference centres)."""
    cols = U[(U > 150) & (U < 200)]
    states = ["A", "B", "AB"] * 4
    t = build(states)
    # laser A also lights a second surface 40 rows above in columns 150..200 (clear of B)
    extra = {k: [] for k in t}
    for f, s in enumerate(states):
        if "A" in s:
            extra["frame"].append(np.full(cols.size, f))
            extra["u"].append(cols)
            extra["v"].append(line("A", f)[np.isin(U, cols)] - 40.0)
            extra["flags"].append(np.zeros(cols.size, np.uint8))
            extra["truth"].append(np.full(cols.size, "A"))
    t = {k: np.concatenate([t[k], *extra[k]]) for k in t}
    # the A frames miss every 7th column (the stripe fell below the threshold there)
    a_frames = np.isin(t["frame"], np.flatnonzero(np.array(states) == "A"))
    drop = a_frames & (t["u"] % 7 == 0) & (t["u"] < U[-1])
    t = {k: x[~drop] for k, x in t.items()}
    o = np.lexsort((t["v"], t["u"], t["frame"]))
    t = {k: x[o] for k, x in t.items()}
    states_a = np.array(states)
    ab = np.isin(t["frame"], np.flatnonzero(states_a == "AB"))
    d = Disambiguator(threshold_px=10, max_frame_gap=3, ambiguity_px=3, predict=False, bridge_columns=4)
    label = np.full(t["u"].size, "", "<U2")
    for f, s in enumerate(states):
        m = t["frame"] == f
        label[m], _ = d.process(f, s, t["u"][m], t["v"][m], t["flags"][m])
    done = label != ""
    assert np.all(label[done] == t["truth"][done])
    away = ab & (sep(t) > 6)
    assert np.all(done[away])  # the gap columns (u % 7 == 0) included
    assert d.counts["dropped"]["conflict"] == 0


def test_tracked_references_follow_an_accelerating_sweep():
    """A, B and four AB frames while the stripes accelerate (the scanner speeds up): the A and
    B frames' own prediction falls behind by the fourth AB frame, the previous AB frame's
    labelled stripes do not."""
    states = ["A", "B", "AB", "AB", "AB", "AB"] * 5
    offset = 0.12 * np.arange(len(states)) ** 2  # rows: 0, 0.1, 0.5, ... 100 at frame 29
    rows = {"frame": [], "u": [], "v": [], "flags": [], "truth": []}
    for f, s in enumerate(states):
        for laser in {"A": "A", "B": "B", "AB": "AB"}[s]:
            rows["frame"].append(np.full(U.size, f))
            rows["u"].append(U)
            rows["v"].append(line(laser, 0) + offset[f])
            rows["flags"].append(np.zeros(U.size, np.uint8))
            rows["truth"].append(np.full(U.size, laser))
    t = {k: np.concatenate(v) for k, v in rows.items()}
    o = np.lexsort((t["v"], t["u"], t["frame"]))
    t = {k: v[o] for k, v in t.items()}
    ab = np.isin(t["frame"], np.flatnonzero(np.array(states) == "AB")) & (sep(t) > 6)
    done = {}
    for track in (False, True):
        d = Disambiguator(threshold_px=10, max_frame_gap=6, ambiguity_px=3, track=track)
        label = np.full(t["u"].size, "", "<U2")
        for f, s in enumerate(states):
            m = t["frame"] == f
            label[m], _ = d.process(f, s, t["u"][m], t["v"][m], t["flags"][m])
        ok = label != ""
        done[track] = (ok[ab].mean(), int((ok & ab & (label != t["truth"])).sum()))
    # away from the crossing, tracked: every AB centre labelled, none wrong; the references of
    # the A and B frames alone lag by up to ~13 rows: centres are lost or mislabelled
    assert done[True][0] > 0.99 and done[True][1] == 0
    assert done[False][0] < 0.9 or done[False][1] > 0


def test_short_label_islands_in_a_stripe_are_dropped_long_runs_stay():
    """Along one stripe: a run of 2 A labels inside B (a stale A reference on the B stripe), a
    lone A label and a short A run among centres left unlabelled, and a longer A run among
    unlabelled centres. All but the last are islands; the longer run is a stripe and stays."""
    from crossline.scan.labels import ISOLATED_MAX, _trace_minority

    u = np.arange(100.0)
    v = 300.0 + 0.4 * u
    lab = np.full(u.size, 2)
    lab[20:22] = 1  # A island inside B
    lab[40:60] = 0  # ambiguous stretch...
    lab[50] = 1  # ...with one A label in it
    lab[60:90] = 0
    lab[64:64 + ISOLATED_MAX] = 1  # a short A run among unlabelled centres: an island too
    lab[78:78 + ISOLATED_MAX + 1] = 1  # a longer one is a stripe
    out = _trace_minority(u, v, lab, np.zeros(u.size, bool))
    assert np.flatnonzero(out).tolist() == [20, 21, 50, *range(64, 64 + ISOLATED_MAX)]
    # a second stripe elsewhere in the frame is a trace of its own: nothing dropped on it
    u2, v2 = np.r_[u, u], np.r_[v, v + 200.0]
    lab2 = np.r_[lab, np.r_[np.full(3, 1), np.full(97, 0)]]  # its first 3 columns labelled A
    out2 = _trace_minority(u2, v2, lab2, np.zeros(u2.size, bool))
    assert np.flatnonzero(out2).tolist() == np.flatnonzero(out).tolist()


def test_island_on_a_stripe_flagged_merged_here_and_there_is_still_an_island():
    """A wide stripe at grazing incidence is flagged merged in scattered columns (demo part,
    frame 70: a stale A reference crossed the B stripe over 3 columns between merged ones).
    Merged centres hold no label but keep the trace whole, so the 3 A labels among the
    unlabelled rest of the stripe are an island; the merged centres themselves are not."""
    from crossline.scan.labels import _trace_minority

    u = np.arange(60.0)
    v = 500.0 + 0.85 * u
    lab = np.zeros(u.size, int)
    lab[30:33] = 1
    merged = np.zeros(u.size, bool)
    merged[[25, 29, 33, 36, 41]] = True
    lab[merged] = 0
    assert np.flatnonzero(_trace_minority(u, v, lab, merged)).tolist() == [30, 31, 32]
    # a labelled stripe interrupted by merged columns is one run, not islands
    lab2 = np.where(merged, 0, 2)
    assert not _trace_minority(u, v, lab2, merged).any()


def test_laser_frame_without_centres_then_with_centres():
    """An A frame with no centre, then an A frame with centres: the next AB frame is labelled
    from the latter, not predicted from an empty frame (which raised IndexError)."""
    states = ["A", "B", "AB", "A", "B", "AB"]
    t = build(states, drop_frames=(0,))
    label, _, counts = run(states, t)
    ab = (t["frame"] == 5) & (sep(t) > 10)
    assert ab.sum() > 200 and np.all(label[ab] == t["truth"][ab])
    assert counts["frames"]["A"] == 2
