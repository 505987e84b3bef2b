"""The tables of experiments/render_compare_real_starts: one per APR (DFNet, PoseNet), a row per
scene and the mean over each dataset, from ``OUT/<scene>/real_starts_<APR>.json`` (and the
truth audit, ``truth_audit.json``: refined from the true poses, a floor that reads the test
labels); a column per recording where run.py refined the recordings too (``--recordings``).

    python experiments/render_compare_real_starts/table.py outputs/render_compare_real_starts
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pae.render_compare.correspondences import MatchSettings

COLUMNS = (
    "scene",
    "start cm / deg",
    "render_compare cm / deg",
    "NeFeS50 (real images) cm / deg",
    "ratio pae / NeFeS50",
    "from truth (audit) cm / deg",
    "within 5 cm, 5° start → pae",
    "accepted",
    "filter: high-pass px / levels / contrast px; surface share (val)",
    "stage (val)",
    "PSNR dB",
    "fit s",
    "ms / query",
)


def cell(figures: dict[str, float]) -> str:
    return f"{100 * figures['pos_median_m']:.1f} / {figures['rot_median_deg']:.2f}"


def row(record: dict, recordings: bool) -> list[str]:
    start, pae, nefes = record["start"], record["render_compare"], record["nefes50"]
    ratio = pae["pos_median_m"] / start["pos_median_m"]
    nefes_ratio = nefes["pos_median_m"] / start["pos_median_m"]
    walked = [cell(record["per_recording"]) if "per_recording" in record else ""] * recordings
    every = record.get("every", 1)
    return [
        record["scene"] + (f" (one test image in {every})" if every > 1 else ""),
        cell(start),
        cell(pae),
        *walked,
        cell(nefes),
        f"{ratio:.2f}× / {nefes_ratio:.2f}×",
        cell(record["audit"]) if "audit" in record else "",
        f"{100 * start['within_5cm_5deg']:.0f} % → {100 * pae['within_5cm_5deg']:.0f} %",
        f"{100 * record['accepted_share']:.0f} %",
        chosen_filter(record["calibration"]),
        chosen_stage(record.get("stage")),
        f"{record['psnr_db']:.1f}" if record.get("psnr_db") is not None else "",
        f"{record['fit_s']:.0f}" if record.get("fit_s") is not None else "",
        f"{record['ms_per_query']:.1f}",
    ]


def chosen_filter(calibration: dict[str, float]) -> str:
    """The filter chosen on val: the high-pass's sigma (px) and the finest levels it applies
    at (all: every level), or none; then the local contrast's sigma (px), the highlight clip's
    quantile, the trim's sigma and the references' surface share where chosen."""
    sigma = calibration.get("highpass_sigma_px", 0.0)
    contrast = calibration.get("contrast_sigma_px", 0.0)
    share = calibration.get("surface_share", 0.0)
    levels = int(calibration.get("highpass_levels", 0))
    chosen = f"{sigma:g} / {levels or 'all'}" if sigma else "none"
    chosen = f"{chosen} / c {contrast:g}" if contrast else chosen
    for key, name in (("highlight_quantile", "clip"), ("trim_sigma", "trim")):
        chosen = f"{chosen} / {name} {calibration[key]:g}" if calibration.get(key) else chosen
    return f"{chosen}; s {share:g}" if share else chosen


def chosen_stage(match: dict | None) -> str:
    """The correspondence stage chosen on val (``pae-localize --summary``'s
    ``calibration.match``; none where none runs)."""
    return MatchSettings(**match).described() if match else "none"


def mean_row(dataset: str, records: list[dict], recordings: bool) -> list[str]:
    def mean(method: str, key: str) -> float:
        return sum(r[method][key] for r in records) / len(records)

    methods = ["start", "render_compare", "nefes50"]
    every = recordings and all("per_recording" in r for r in records)
    figures = {
        method: {k: mean(method, k) for k in ("pos_median_m", "rot_median_deg")}
        for method in methods + ["per_recording"] * every
    }
    ratio = figures["render_compare"]["pos_median_m"] / figures["start"]["pos_median_m"]
    nefes = figures["nefes50"]["pos_median_m"] / figures["start"]["pos_median_m"]
    return [
        f"**{dataset} mean ({len(records)})**",
        cell(figures["start"]),
        cell(figures["render_compare"]),
        *[cell(figures["per_recording"]) if every else ""] * recordings,
        cell(figures["nefes50"]),
        f"{ratio:.2f}× / {nefes:.2f}×",
        *[""] * 8,
    ]


def main(argv: list[str]) -> int:
    out = Path(argv[0] if argv else "outputs/render_compare_real_starts")
    for apr in ("DFNet", "PoseNet"):
        records = []
        for path in sorted(out.glob(f"*/real_starts_{apr}.json")):
            record = json.loads(path.read_text())
            audit = path.parent / "truth_audit.json"
            if audit.is_file():
                record["audit"] = json.loads(audit.read_text())["from_truth_oracle"]
            summary = path.parent / f"render_compare_{apr}.json"
            if summary.is_file():
                record["stage"] = json.loads(summary.read_text())["calibration"].get("match")
            records.append(record)
        if not records:
            continue
        print(f"\n{apr} starts (median cm / deg over each scene's test images)\n")
        recordings = any("per_recording" in r for r in records)
        columns = list(COLUMNS)
        if recordings:
            columns.insert(3, "per recording cm / deg")
        print("| " + " | ".join(columns) + " |")
        print("|" + "---|" * len(columns))
        for dataset in ("7Scenes", "Cambridge"):
            members = [r for r in records if r["dataset"] == dataset]
            for record in members:
                print("| " + " | ".join(row(record, recordings)) + " |")
            if members:
                print("| " + " | ".join(mean_row(dataset, members, recordings)) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
