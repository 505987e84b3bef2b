"""`pae-export RUN OUT`: a finished run's teacher and student PAE as ONNX files, with the
pre-processing beside them (pae.apps.export)."""

from __future__ import annotations

import argparse
from pathlib import Path

EPILOG = """examples:
  pae-export outputs/demo outputs/demo/onnx
  pae-localize outputs/demo my_images/ --onnx outputs/demo/onnx --out poses.csv
OUT gets teacher.onnx (image -> pose, latent and, for a multi-scene teacher, scene logits),
pae.onnx (pose -> latent; where the run trained a student) and pae_export.json (their inputs
and outputs, the pre-processing, the scenes, the training data's fingerprint)."""


def parser() -> argparse.ArgumentParser:
    """The command line of pae-export."""
    parse = argparse.ArgumentParser(
        prog="pae-export",
        description="A finished pae-train run's teacher and PAE as ONNX files.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parse.add_argument("run_dir", type=Path, help="a finished run directory (e.g. outputs/demo)")
    parse.add_argument("out", type=Path, help="the folder to write the files into")
    return parse


def main(argv: list[str] | None = None) -> int:
    """Export the run's networks into OUT; each file is written whole."""
    args = parser().parse_args(argv)
    from pae.core.console import quiet_third_party
    from pae.core.error_reporting import reporting_errors

    quiet_third_party()
    with reporting_errors("pae-export"):
        from pae.apps.export import MANIFEST, export_run

        manifest = export_run(args.run_dir, args.out)
        files = [manifest[part]["file"] for part in ("teacher", "pae") if part in manifest]
        print(f"pae-export: {', '.join(files)} and {MANIFEST} in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
