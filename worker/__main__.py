"""``python -m worker``: start a Celery worker with the service's defaults.

    python -m worker --queues cpu --concurrency 1     # retarget jobs on the CPU
    python -m worker --queues gpu                     # retarget jobs on a GPU machine
    python -m worker --queues io --concurrency 2      # upload parsing, body making
    python -m worker --queues webhooks                # callback deliveries (threads; no library import)
"""

from __future__ import annotations

import argparse
import os


def preload() -> None:
    """Import the library once in the parent so each forked job process starts without paying for it."""
    try:
        import retarget_core.inspect  # noqa: F401
        import retarget_core.pipeline  # noqa: F401
    except ImportError as exc:  # the worker still starts; jobs then fail with a clear internal error
        print(f"warning: retarget_core could not be imported: {exc}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m worker", description="Start a worker of the service")
    parser.add_argument("--queues", "-Q", default="cpu", help="comma-separated: cpu, gpu, io (default cpu)")
    parser.add_argument("--concurrency", "-c", type=int, default=None,
                        help="processes (threads for the webhooks queue); default 1 (8 for webhooks)")
    parser.add_argument("--pool", default=None, choices=("prefork", "threads", "solo"),
                        help="default prefork; threads when the only queue is webhooks")
    parser.add_argument("--name", "-n", default=None, help="node name (default <queues>-<pid>@<host>)")
    parser.add_argument("--loglevel", "-l", default=os.environ.get("RETARGET_WORKER_LOGLEVEL", "INFO"))
    parser.add_argument("--migrate", action="store_true", help="upgrade the database schema first")
    args = parser.parse_args(argv)
    if args.migrate:
        from api.migrate import upgrade

        upgrade()
    from worker.app import app

    only_webhooks = set(args.queues.split(",")) == {"webhooks"}
    pool = args.pool or ("threads" if only_webhooks else "prefork")
    concurrency = args.concurrency or (8 if only_webhooks else 1)
    if not only_webhooks:
        preload()

    name = args.name or f"{args.queues.replace(',', '+')}-{os.getpid()}@%h"
    app.worker_main([
        "worker", "--queues", args.queues, "--concurrency", str(concurrency), "--hostname", name,
        "--pool", pool, "--loglevel", args.loglevel, "--without-gossip", "--without-mingle",
    ])


if __name__ == "__main__":
    main()
