"""`occflownet serve`: serve an exported ONNX model over HTTP (FastAPI + uvicorn + onnxruntime, no torch).

Options left unset fall back to the ``OCCFLOWNET_*`` environment variables and a ``.env`` file (see
serve/settings.py), then to the defaults. With ``--workers N`` the settings reach the workers through the
environment, and their metrics are kept in one ``PROMETHEUS_MULTIPROC_DIR`` folder (made and removed here) so that
``/metrics`` answers for all of them. The model is checked before uvicorn starts, so a missing or invalid file ends the command with a message
naming it (exit status 2). The API key is read from ``OCCFLOWNET_API_KEY`` only (never a command-line argument,
which other users could read from the process list).
"""
import os
import sys

HELP = "serve an ONNX model over HTTP"


def add_arguments(parser):
    parser.add_argument("--model", help="contract-v1 ONNX file (default: $OCCFLOWNET_MODEL)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    parser.add_argument("--workers", type=int, default=None,
                        help="uvicorn worker processes, each with its own model session (default 1)")
    parser.add_argument("--threads", type=int, default=None, dest="intra_op_threads",
                        help="onnxruntime intra-op threads per inference (default: cores // workers)")
    parser.add_argument("--max-inflight", type=int, default=None,
                        help="concurrent inferences per worker (default: max(1, cores // workers // threads))")
    parser.add_argument("--max-queue", type=int, default=None,
                        help="requests admitted beyond those running; more get 503 + Retry-After (default 4)")
    parser.add_argument("--max-body-mb", type=float, default=None, help="request body limit in MiB (default 64)")
    parser.add_argument("--max-image-pixels", type=int, default=None,
                        help="pixels per image, checked from the header before decoding (default 4096*4096)")
    parser.add_argument("--no-warmup", action="store_true", help="ready at once, without a warm-up inference")
    parser.add_argument("--no-ui", action="store_true", help="no browser page at /ui: the API only")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    parser.add_argument("--no-access-log", action="store_true", help="do not log one line per request")


def _settings(args):
    """The options given, over the environment (``ServeSettings.from_env``: a bad value raises SettingsError)."""
    from occflownet.serve.settings import ServeSettings

    body = None if args.max_body_mb is None else int(args.max_body_mb * 1024 * 1024)
    return ServeSettings.from_env(model_path=args.model, workers=args.workers, intra_op_threads=args.intra_op_threads,
                                  max_inflight=args.max_inflight, max_queue=args.max_queue,
                                  max_image_pixels=args.max_image_pixels, max_body_bytes=body,
                                  warmup=False if args.no_warmup else None, ui=False if args.no_ui else None)


def run(args) -> int:
    try:
        settings = _settings(args)
        resolved = settings.resolved()
    except ValueError as exc:
        print(f"occflownet serve: {exc}", file=sys.stderr)
        return 2
    if not settings.model_path:
        print("occflownet serve: no model given: pass --model FILE or set OCCFLOWNET_MODEL", file=sys.stderr)
        return 2

    from occflownet.serve.malloc import cap_malloc_arenas

    cap_malloc_arenas()  # before onnxruntime and uvicorn start their threads
    import uvicorn

    from occflownet.serve.app import create_app
    from occflownet.serve.metrics import multiprocess_dir
    from occflownet.serve.model_runtime import ModelLoadError, ModelRuntime

    try:
        runtime = ModelRuntime.load(settings.model_path, resolved)
    except ModelLoadError as exc:
        print(f"occflownet serve: {exc}", file=sys.stderr)
        return 2
    md = runtime.metadata
    print(f"occflownet serve: model {runtime.path} (preset {md.preset}, contract {md.onnx_contract}) on "
          f"http://{args.host}:{args.port} with {resolved.workers} worker(s)", file=sys.stderr)
    common = dict(host=args.host, port=args.port, log_level=args.log_level, access_log=not args.no_access_log)
    try:
        if resolved.workers == 1:
            uvicorn.run(create_app(settings, runtime=runtime), **common)
        else:
            del runtime  # each worker process loads its own session from the environment
            os.environ.update(settings.to_env())
            with multiprocess_dir():  # one metrics folder for the workers: /metrics answers for all of them
                uvicorn.run("occflownet.serve.app:create_app_from_env", factory=True, workers=resolved.workers,
                            **common)
    except SystemExit as exc:  # uvicorn exits 3 when start-up fails (e.g. the port is taken)
        return int(exc.code or 0)
    return 0
