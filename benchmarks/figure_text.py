"""How tall each figure's text is where the web book shows it, measured while the lessons execute.

    python benchmarks/figure_text.py 01_synthetic_dataset 03_losses_explained --out benchmarks/figure_text.json

Each notebook is executed by papermill into a temporary folder (the committed notebook is not
touched), in a kernel whose IPython start-up file wraps matplotlib's ``print_figure``: every figure
the lesson shows is measured by ``viz.text_heights_px`` (pixels tall at ``viz.BOOK_COLUMN_PX``)
before it is drawn. The record holds, per notebook, each figure's width, its number of texts, its
least text height and how many texts are under ``viz.MIN_TEXT_PX``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from geodepth_lite import utils  # noqa: E402
from geodepth_lite.views import viz  # noqa: E402

HOOK = '''
import json, os
import matplotlib.backend_bases as bb
_print_figure = bb.FigureCanvasBase.print_figure
def _measured(self, *args, **kwargs):
    try:  # a measurement never stops the lesson: a failure is recorded instead
        from geodepth_lite.views import viz
        heights = viz.text_heights_px(self.figure)
        row = {"width_in": round(float(self.figure.get_figwidth()), 2), "texts": len(heights),
               "least_px": round(float(heights[0][1]), 2) if heights else None,
               "below": int(sum(px < viz.MIN_TEXT_PX for _, px in heights))}
    except Exception as exc:
        row = {"error": repr(exc), "texts": 0}
    with open(os.environ["FIGURE_TEXT_LOG"], "a") as f:
        f.write(json.dumps(row) + "\\n")
    return _print_figure(self, *args, **kwargs)
bb.FigureCanvasBase.print_figure = _measured
'''


def measure(name: str, work: Path) -> dict:
    import papermill

    startup = work / "ipython" / "profile_default" / "startup"
    startup.mkdir(parents=True, exist_ok=True)
    (startup / "00_figure_text.py").write_text(HOOK)
    log = work / f"{name}.jsonl"
    env = {"IPYTHONDIR": str(work / "ipython"), "FIGURE_TEXT_LOG": str(log), "MPLBACKEND": "agg",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        papermill.execute_notebook(str(ROOT / "notebooks" / f"{name}.ipynb"), str(work / f"{name}.ipynb"),
                                   parameters={}, kernel_name="python3", cwd=str(ROOT / "notebooks"),
                                   progress_bar=False)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    shown = [r for r in rows if r["texts"]]
    return {"figures": rows, "least_px": min((r["least_px"] for r in shown), default=None),
            "figures_below": sum(r["below"] > 0 for r in shown), "errors": sum("error" in r for r in rows)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("notebooks", nargs="+", help="notebook names without .ipynb")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    record = {"book_column_px": viz.BOOK_COLUMN_PX, "figure_dpi": viz.FIGURE_DPI, "min_text_px": viz.MIN_TEXT_PX,
              "notebooks": {}}
    with tempfile.TemporaryDirectory(prefix="figure-text-") as work:
        for name in args.notebooks:
            record["notebooks"][name] = measure(name, Path(work))
            r = record["notebooks"][name]
            print(f"{name}: {len(r['figures'])} figures drawn, least text {r['least_px']} px, "
                  f"{r['figures_below']} with text under {viz.MIN_TEXT_PX} px", flush=True)
    utils.write_json_atomic(args.out, record)  # whole or not at all
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
