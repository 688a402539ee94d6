"""The plain-text table `dali eval` prints: AP_BEV, AP_3D, APH and AOS per difficulty or band,
with the match counts, and the notes on sets too small for R40 to reach 100."""

from __future__ import annotations


def format_table(metrics: dict) -> str:
    """A plain-text table: AP_BEV / AP_3D per difficulty or band, with the match counts."""
    lines = []
    for class_name, result in metrics.items():
        lines.append(
            f"{class_name} AP_R{result['recall_positions']} @ IoU {result['iou']:g} "
            f"(protocol {result['protocol']}, {result['frames']} frames)"
        )
        image = "bbox" in result  # KITTI's image side: AP_2D, and AOS matched on it
        header = f"{'':<10}{'AP_BEV':>8}{'AP_3D':>8}" + (f"{'AP_2D':>8}" if image else "")
        header += f"{'APH':>8}{'AOS':>8}{'GT':>8}{'ign':>6}"
        header += f"{'pred':>8}{'TP/FP/FN (BEV)':>22}{'TP/FP/FN (3D)':>22}{'backwards':>12}"
        lines.append(header)
        for name in result["bev"]:
            counts = result["counts"][name]
            headings = (result.get("aph", {}).get(name), result.get("aos", {}).get(name))

            def show(value):
                return f"{value:8.2f}" if value is not None else f"{'-':>8}"

            row = f"{name:<10}{show(result['bev'][name])}{show(result['3d'][name])}"
            row += show(result["bbox"][name]) if image else ""
            row += f"{show(headings[0])}{show(headings[1])}"
            row += f"{counts['gt']:>8}{counts['gt_ignored']:>6}{counts['pred']:>8}"
            for metric in ("bev", "3d"):
                totals = counts[metric]
                row += f"{totals['tp']:>10}/{totals['fp']}/{totals['fn']}".rjust(22)
            heading = result.get("heading", {}).get(name)
            if heading and heading["tp"]:
                row += f"{heading['backwards']}/{heading['tp']}".rjust(12)
            lines.append(row)
        lines.append(
            "APH, AOS: AP with each true positive weighted by its heading (Waymo's 1 - |dθ|/π "
            "on the BEV matches, KITTI's (1 + cos dθ)/2 "
            + (
                f"on the image matches at 2D IoU > {result['bbox_iou']:g}, dθ of alpha; AP_2D: "
                "those matches' AP"
                if image
                else "on the BEV matches"
            )
            + "); backwards: true positives facing > 90° away"
        )
        lines.extend(ceiling_notes(result))
    return "\n".join(lines)


def ceiling_notes(result: dict) -> list[str]:
    """One line per group whose AP cannot reach 100 with so few counted ground truths (a
    class's `evaluate` result; none when every group can, or under R400)."""
    notes = []
    for name, counts in result["counts"].items():
        ceiling = counts.get("ap_ceiling")
        if ceiling is not None and ceiling < 100.0:
            notes.append(
                f"{name}: only {counts['gt']} ground truths count: a perfect detector scores "
                f"{ceiling:.2f} under R{result['recall_positions']} (the KITTI reference samples "
                f"one threshold per true positive below 41); --recall-positions 400 reads the "
                f"precision at exact recalls"
            )
    return notes
