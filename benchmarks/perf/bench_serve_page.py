"""How much the server page (``GET /ui``) adds to the API's own round trip, in headless Chromium on this machine.

Starts ``occflownet serve`` (a real uvicorn process) with the tests' briefly trained tiny model (or ``--model``),
opens ``/ui`` in the browser of the tests (``tests/browser.py``: SwiftShader WebGL), sends the real nuScenes frame
(six JPEGs and calib.json) once to warm up, then measures, interleaved and in alternating order, the API's round
trip of the same request by httpx and the page's (click → answer on screen: top-down picture and latencies; then →
3D view drawn, its first frame read back), ``benchmarks.harness.interleaved``: ``--pairs`` pairs a round,
``--rounds`` rounds, each pair printed, and per round the median over its pairs of page − API with the load average
and the float32 matmul rate (appended to ``--jsonl``). Target: the page adds ≤ 150 ms until the answer is on screen.

    python -m benchmarks.perf.bench_serve_page [--model model.onnx] [--pairs 5] [--rounds 3] [--jsonl PATH]
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks.harness import REPO, Results, add_jsonl_option, interleaved, tree_env
from occflownet.serve.client import wait_ready
from tests.browser import browser, setup_browser, wait_for
from tests.serve_fixtures import free_port, post_frame, send_from_page, stop_server

TARGET_MS = 150.0


def one_round(server: str, page, pairs: int) -> dict[str, float]:
    """``pairs`` interleaved pairs, the order alternating → {"shown", "drawn", "api"}: medians over the pairs of
    page − API (answer on screen, 3D view drawn) and of the API's round trip, in ms."""
    rows = []
    runs = interleaved({"api": lambda: post_frame(server)[1], "page": lambda: send_from_page(page)}, pairs)
    for (_, api_ms), (_, last) in zip(runs["api"], runs["page"]):
        assert last["ok"] and last["status"] == 200, last
        rows.append((api_ms, last["shownMs"], last["drawnMs"]))
        t = last["viewer"]["timings"]
        print(f"  API {api_ms:.0f} ms; page: answer {last['fetchMs']:.0f} ms, shown {last['shownMs']:.0f} ms, 3D "
              f"{last['drawnMs']:.0f} ms (surface {t['built'] - t['decoded']:.0f}, first frame "
              f"{last['viewer']['firstFrameMs'] - t['built']:.0f} ms); server total {last['server']['total']:.0f} ms")
    pane = last["viewer"]["panes"][0]
    print(f"  ({pane['voxels']} voxels, {pane['quads']} rectangles)")
    return {"shown": statistics.median(s - a for a, s, _ in rows), "drawn": statistics.median(d - a for a, _, d in rows),
            "api": statistics.median(a for a, _, _ in rows)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="contract-v1 ONNX model (default: the tests' briefly trained tiny export)")
    parser.add_argument("--pairs", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=3)
    add_jsonl_option(parser)
    args = parser.parse_args()
    results = Results("bench_serve_page", args.jsonl)
    if args.model:
        model = Path(args.model)
    else:
        from tests.exported_models import exported_trained_tiny

        model = exported_trained_tiny()[0]
    setup_browser()
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "occflownet", "serve", "--model", str(model), "--port", str(port),
                             "--no-access-log", "--log-level", "warning"], cwd=REPO, env=tree_env())
    server = f"http://127.0.0.1:{port}"
    try:
        wait_ready(server, 120, proc=proc)
        with browser() as page:
            page.get(f"{server}/ui")
            wait_for(page, "window.occPage && window.occPage.metadata")
            assert send_from_page(page)["ok"]                       # warm: the first canvas, the first upload
            for r in range(args.rounds):
                print(f"round {r + 1}:")
                result = one_round(server, page, args.pairs)
                results.add({"round": r + 1, "pairs": args.pairs, "api_ms": result["api"],
                             "page_adds_shown_ms": result["shown"], "page_adds_drawn_ms": result["drawn"]},
                            f"round {r + 1}: API round trip p50 {result['api']:.0f} ms; the page adds "
                            f"{result['shown']:.0f} ms to the answer on screen (target ≤ {TARGET_MS:.0f} ms), "
                            f"{result['drawn']:.0f} ms to the 3D view drawn (medians of {args.pairs} pairs)")
    finally:
        stop_server(proc)


if __name__ == "__main__":
    main()
