"""`occflownet serve`: serve an exported ONNX model over HTTP (FastAPI + uvicorn + onnxruntime, no torch).

The options are the fields of ``serve.settings.ServeSettings`` (``occflownet/options.py`` ``add_model_options``:
names, help and the defaults shown come from the fields), but the API key, which is read from
``OCCFLOWNET_API_KEY`` only (never a command-line argument, which other users could read from the process list),
and the body limit, given in MiB (``--max-body-mb``) where the setting counts bytes; plus uvicorn's ``--host``,
``--port``, ``--log-level`` and ``--no-access-log``. Options left unset fall back to the ``OCCFLOWNET_*``
environment variables and a ``.env`` file, then to the defaults. With ``--workers N`` the settings reach the workers
through the environment, and their metrics are kept in one ``PROMETHEUS_MULTIPROC_DIR`` folder (made and removed
here) so that ``/metrics`` answers for all of them. Before uvicorn starts, the command checks that it can bind the
address (a port outside 0..65535, or one already in use, ends it with one line) and checks the model (a missing,
unreadable or invalid file, or an execution provider this onnxruntime lacks, ends it with a line naming it); exit
status 2 for each. SIGTERM waits at most ``shutdown_timeout_s`` for the requests in flight.
"""
import contextlib
import os
import socket
import sys

from occflownet.options import add_model_options, model_kwargs

HELP = "serve an ONNX model over HTTP"
NOT_OPTIONS = ("api_key", "max_body_bytes")  # the key: environment only; the body limit: --max-body-mb
MIB = 1024 * 1024
NEEDS_EXTRA = "needs the serve extra (pip install 'occflownet[serve]')"


def add_arguments(parser):
    try:
        from occflownet.serve.settings import ServeSettings, env_name
    except ImportError as exc:  # an install without the serve extra: the other verbs still start
        parser.description = f"{HELP}: {NEEDS_EXTRA}"
        parser.set_defaults(missing_extra=str(exc))
        return
    add_model_options(parser, ServeSettings, skip=NOT_OPTIONS, env=env_name)
    body = ServeSettings.model_fields["max_body_bytes"]
    parser.add_argument("--max-body-mb", type=float, default=None,
                        help=f"{body.description} in MiB (default: {body.default / MIB:g}; "
                             f"${env_name('max_body_bytes')} in bytes)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port, 0..65535 (default 8000)")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    parser.add_argument("--no-access-log", action="store_true", help="do not log one line per request")


def _settings(args):
    """The options given, over the environment (``ServeSettings.from_env``: a bad value raises SettingsError)."""
    from occflownet.serve.settings import ServeSettings

    body = None if args.max_body_mb is None else int(args.max_body_mb * MIB)
    return ServeSettings.from_env(**model_kwargs(args, ServeSettings, skip=NOT_OPTIONS), max_body_bytes=body)


def run(args) -> int:
    if getattr(args, "missing_extra", None):
        print(f"occflownet serve {NEEDS_EXTRA}: {args.missing_extra}", file=sys.stderr)
        return 2
    try:
        settings = _settings(args)
        resolved = settings.resolved()
    except ValueError as exc:
        print(f"occflownet serve: {exc}", file=sys.stderr)
        return 2
    if not settings.model_path:
        print("occflownet serve: no model given: pass --model FILE or set OCCFLOWNET_MODEL", file=sys.stderr)
        return 2
    try:
        _check_address(args.host, args.port)
    except OSError as exc:
        print(f"occflownet serve: cannot listen on {args.host}:{args.port}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return _serve(args, settings, resolved)


def _check_address(host: str, port: int) -> None:
    """OSError unless a TCP socket can be bound to ``host``:``port`` as uvicorn binds its own (IPv6 when the host
    has a colon, SO_REUSEADDR): the port outside 0..65535, the address in use or not of this machine."""
    if not 0 <= port <= 65535:
        raise OSError(f"port {port} is outside 0..65535")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind((host, port))


def _serve(args, settings, resolved) -> int:
    """Load and check the model, then run uvicorn: in this process (one worker) or in ``workers`` processes under
    uvicorn's supervisor → the exit status."""
    from occflownet.serve.malloc import cap_malloc_arenas

    cap_malloc_arenas()  # before onnxruntime and uvicorn start their threads
    import uvicorn

    from occflownet.serve.app import create_app
    from occflownet.serve.metrics import multiprocess_dir, multiprocess_enabled
    from occflownet.serve.model_runtime import ModelLoadError, ModelRuntime

    try:
        runtime = ModelRuntime.load(settings.model_path, resolved)
    except ModelLoadError as exc:
        print(f"occflownet serve: {exc}", file=sys.stderr)
        return 2
    md = runtime.metadata
    print(f"occflownet serve: model {runtime.path} (preset {md.preset}, contract {md.onnx_contract}) on "
          f"http://{args.host}:{args.port} with {resolved.workers} worker(s)", file=sys.stderr)
    common = dict(host=args.host, port=args.port, log_level=args.log_level, access_log=not args.no_access_log,
                  timeout_graceful_shutdown=settings.shutdown_timeout_s)
    try:
        if resolved.workers == 1:
            # a PROMETHEUS_MULTIPROC_DIR of the environment puts the metrics there: the folder is made and cleaned
            with multiprocess_dir() if multiprocess_enabled() else contextlib.nullcontext():
                uvicorn.run(create_app(settings, runtime=runtime), **common)
        else:
            del runtime  # each worker process loads its own session from the environment
            os.environ.update(settings.to_env())
            with multiprocess_dir():  # one metrics folder for the workers: /metrics answers for all of them
                uvicorn.run("occflownet.serve.app:create_app_from_env", factory=True, workers=resolved.workers,
                            **common)
    except SystemExit as exc:  # uvicorn exits 3 when start-up fails (e.g. the port was taken in the meantime)
        return int(exc.code or 0)
    return 0
