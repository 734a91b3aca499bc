"""``canopy-kit evaluate RUN_DIR --truth SIM_DIR``: score a segmentation against truth."""

from __future__ import annotations

from pathlib import Path

import typer


def evaluate(
    run_dir: Path = typer.Argument(
        ..., help="Folder written by 'canopy-kit segment' or 'canopy-kit run'"
    ),
    truth: Path = typer.Option(..., "--truth", help="Simulated session folder (with truth/)"),
    mode: str = typer.Option(
        "auto", help="points, footprints or auto (points when the map carries per-point truth)"
    ),
    min_iou: float = typer.Option(0.5, "--min-iou", help="IoU for a tree to count as correct"),
    json_output: bool = typer.Option(False, "--json", help="Print the scores as JSON"),
) -> None:
    """Per-tree segmentation success, over/under-segmentation, precision/recall, labels."""
    from canopy_kit.cli.common import print_json
    from canopy_kit.evaluate.segmentation_score import evaluate_run

    score = evaluate_run(run_dir, truth, min_iou=min_iou, mode=mode)
    if json_output:
        data = score.to_dict()
        data["trees"] = score.trees.to_dict(orient="records")
        print_json(data)
        return
    from canopy_kit.cli.tables import Grid, print_grid

    d = score.to_dict()
    table = Grid(
        ["measure", "value"],
        header=False,
        right={1},
        wrap={0},
        title=f"segmentation vs truth ({d['mode']} IoU ≥ {d['min_iou']})",
    )
    table.add_row("true trees", str(d["n_truth"]))
    table.add_row("predicted segments", str(d["n_predicted"]))
    table.add_row("correct (success rate)", f"{d['n_correct']} ({d['success_rate']:.1%})")
    table.add_row(
        "merged / split / missed / other",
        f"{d['n_merged']} / {d['n_split']} / {d['n_missed']} / {d['n_other']}",
    )
    table.add_row(
        "precision / recall / F1", f"{d['precision']:.3f} / {d['recall']:.3f} / {d['f1']:.3f}"
    )
    table.add_row("segments that are no tree", str(d["n_false_segments"]))
    table.add_row(
        "labels correct (of correct trees)", f"{d['n_label_correct']} ({d['label_accuracy']:.1%})"
    )
    print_grid(table)
