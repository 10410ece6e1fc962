"""The optional back ends of a sweep: a Ray cluster, and Parquet output.

Both are extras (``pip install 'bess-ded[ray]'``, ``'bess-ded[parquet]'``) so that the
base install stays small; asking for one that is not installed is a usage error naming
the extra. ``--ray local`` starts Ray's own local cluster (what the tests use);
any other address is passed to ``ray.init`` (``auto``, ``ray://host:10001``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from firmware_py.errors import BessDedError

Row = dict[str, Any]


class MissingExtraError(BessDedError):
    """An optional dependency the command needs is not installed (exit 2, as bad input)."""


def _need(module: str, extra: str, option: str) -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(f"{option}: expected the {extra} extra (pip install "
                                f"'bess-ded[{extra}]'), but {module} is not installed") from None


def ray_executor(address: str) -> Callable[[list[Row]], Iterator[tuple[Row, Row]]]:
    """A sweep executor that runs each point as a Ray task on the cluster at ``address``
    and yields (params, row) as tasks finish."""
    ray = _need("ray", "ray", "--ray")

    def execute(todo: list[Row]) -> Iterator[tuple[Row, Row]]:
        from sim.study.sweep import run_point

        started = not ray.is_initialized()
        if started:
            ray.init(address=None if address == "local" else address,
                     include_dashboard=False, log_to_driver=False)
        try:
            task = ray.remote(run_point)
            pending = {task.remote(p): p for p in todo}
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    yield pending.pop(ref), ray.get(ref)
        finally:
            if started:  # a local cluster Ray started for us goes with it
                ray.shutdown()

    return execute


def write_parquet(csv_path: Path) -> Path:
    """``csv_path`` as a Parquet table beside it (same columns, typed by pyarrow)."""
    _need("pyarrow", "parquet", "--parquet")
    from pyarrow import csv as pacsv
    from pyarrow import parquet as pq

    out = csv_path.with_suffix(".parquet")
    pq.write_table(pacsv.read_csv(csv_path), out)
    return out
