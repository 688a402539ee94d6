"""An independent port of the eval loop of OpenPCDet's kitti_object_eval_python (eval.py:
clean_data's flags aside, compute_statistics_jit and get_thresholds), written from its source
line by line rather than from dali's evaluator, which tests/test_evaluate.py and
tests/test_image_aos.py check against it."""

from __future__ import annotations


def reference_statistics(
    overlaps, scores, ignored_gt, ignored_dt, min_overlap, thresh, compute_fp, similarity=None
):
    """compute_statistics_jit of one frame: (tp, fp, fn, true-positive scores, orientation
    similarity). `overlaps[j, i]`: detection j against ground truth i; ignore flags 0 counted,
    1 ignored, -1 another class; `similarity[j, i]` (optional): (1 + cos dθ) / 2, summed over
    the true positives (KITTI's AOS)."""
    no_detection = -10000000
    assigned = [False] * len(scores)
    below = [compute_fp and s < thresh for s in scores]
    tp = fp = fn = 0
    similar = 0.0
    thresholds = []
    for i in range(len(ignored_gt)):
        if ignored_gt[i] == -1:
            continue
        det, valid, max_overlap, took_ignored = -1, no_detection, 0, False
        for j in range(len(scores)):
            if ignored_dt[j] == -1 or assigned[j] or below[j]:
                continue
            overlap = overlaps[j, i]
            if not compute_fp and overlap > min_overlap and scores[j] > valid:
                det, valid = j, scores[j]
            elif (
                compute_fp
                and overlap > min_overlap
                and (overlap > max_overlap or took_ignored)
                and ignored_dt[j] == 0
            ):
                max_overlap, det, valid, took_ignored = overlap, j, 1, False
            elif (
                compute_fp
                and overlap > min_overlap
                and valid == no_detection
                and ignored_dt[j] == 1
            ):
                det, valid, took_ignored = j, 1, True
        if valid == no_detection and ignored_gt[i] == 0:
            fn += 1
        elif valid != no_detection and (ignored_gt[i] == 1 or ignored_dt[det] == 1):
            assigned[det] = True
        elif valid != no_detection:
            tp += 1
            thresholds.append(scores[det])
            if similarity is not None:
                similar += similarity[det, i]
            assigned[det] = True
    if compute_fp:
        fp = sum(
            1
            for j in range(len(scores))
            if not (assigned[j] or ignored_dt[j] == -1 or ignored_dt[j] == 1 or below[j])
        )
    return tp, fp, fn, thresholds, similar


def reference_thresholds(scores, num_gt):
    """get_thresholds: the scores at the 41 recall positions of R40 (KITTI's sampling)."""
    scores = sorted(scores, reverse=True)
    current, chosen = 0.0, []
    for i, score in enumerate(scores):
        left = (i + 1) / num_gt
        right = (i + 2) / num_gt if i < len(scores) - 1 else left
        if (right - current) < (current - left) and i < len(scores) - 1:
            continue
        chosen.append(score)
        current += 1 / 40.0
    return chosen
