"""Where the meta models are fitted: on this machine, or on a Dask cluster (``--scheduler``).

``lmd-train``, ``lms-train`` and ``mimo-train`` fit every model through a backend with two
methods, ``fit`` (the signature of ``meta_model.fit_estimator``) and ``fit_folds`` (that
of ``meta_model.fit_folds``: one model per grouped cross-validation fold):

* :class:`LocalTraining`: ``meta_model`` on this machine, one model after the other;
* :class:`DaskTraining`: XGBoost models fitted with ``xgboost.dask`` on the workers of a
  Dask cluster. The training rows are sent to the workers once per feature matrix, in
  row blocks spread evenly over the workers; each fold's rows and targets are selected
  on the workers, so the folds of the grouped cross validation (``meta_model.group_folds``,
  by sequence / bag) are fitted there too, one after the other, each on every worker.
  The hyper-parameters are ``meta_model.make_estimator``'s. The fitted booster is loaded
  into that plain ``XGBClassifier`` / ``XGBRegressor``, so the model file, manifest and
  feature schema are those of a single-machine run and the nodes load it unchanged.
  Predictions and metrics are computed on this machine.

``--scheduler`` (:func:`training_backend`): ``tcp://HOST:PORT`` (any Dask address), a
scheduler file (``dask scheduler --scheduler-file PATH``), or ``local`` / ``local:N``: a
``distributed.LocalCluster`` of N single-threaded worker processes (default: one per CPU),
started for the run and stopped after it. Workers need the same xgboost as this machine
(nothing of ours runs on them). Other estimator kinds than ``xgboost`` have no distributed
fit: with ``--scheduler`` they are refused with that reason (train them without it).

Results differ slightly from a single-machine fit (each worker sketches its own feature
histograms and draws its own row subsample), by well under 0.005 held-out AUROC on the
meta data (README); the same command on the same cluster gives the same models.
The training data still passes through this process (it reads the tables or bags).
"""
from __future__ import annotations

import contextlib
import os
import re
from pathlib import Path
from typing import Iterator

import numpy as np

from lidar_quality_core import meta_model

__all__ = ["LocalTraining", "DaskTraining", "parse_scheduler", "check_scheduler",
           "training_backend", "add_scheduler_option", "SCHEDULER_HELP"]

SCHEDULER_HELP = ("fit the XGBoost models with xgboost.dask on a Dask cluster: "
                  "tcp://HOST:PORT, a scheduler file, or local / local:N (a local cluster "
                  "of N worker processes, default one per CPU); default: this process")
#: Most rows in one block sent to a worker: a few blocks per worker keep the transfers
#: and the per-partition work of xgboost.dask moderate for large tables.
BLOCK_ROWS = 500_000


class LocalTraining:
    """Fits on this machine with ``meta_model`` (the trainers' default)."""

    scheduler = None

    def fit(self, kind, task, X, y, *, seed: int = 0, n_jobs: int = 1):
        return meta_model.fit_estimator(kind, task, X, y, seed=seed, n_jobs=n_jobs)

    def fit_folds(self, kind, task, X, y, folds, *, seed: int = 0, n_jobs: int = 1):
        return meta_model.fit_folds(kind, task, X, y, folds, seed=seed, n_jobs=n_jobs)

    def record(self) -> dict | None:
        """What a manifest says about where the models were fitted (nothing: here)."""
        return None


class DaskTraining:
    """Fits XGBoost models with ``xgboost.dask`` through ``client`` (module docstring)."""

    def __init__(self, client, scheduler: str = ""):
        self.client = client
        self.scheduler = scheduler
        # the last matrix and targets sent (one matrix serves many fits) and their blocks
        self._last_X = self._last_y = None

    @property
    def workers(self) -> list[str]:
        """Worker addresses in xgboost.dask's rank order (by its task id of the worker's
        name and address): block k goes to rank k, so a run does not depend on the ports
        the workers happened to get."""
        info = self.client.scheduler_info()["workers"]
        return sorted(info, key=lambda a: f"[xgboost.dask-{info[a].get('name')}]:{a}")

    def record(self) -> dict:
        return {"scheduler": self.scheduler, "workers": len(self.workers),
                "library": "xgboost.dask"}

    # -- data on the workers
    def _blocks(self, n: int) -> list[tuple[int, int, str]]:
        """``(first row, end row, worker)`` of each block, round robin over the workers."""
        workers = self.workers
        k = max(len(workers), -(-n // BLOCK_ROWS), 1)
        edges = np.linspace(0, n, k + 1).astype(int)
        return [(int(a), int(b), workers[j % len(workers)])
                for j, (a, b) in enumerate(zip(edges[:-1], edges[1:])) if b > a]

    def _scatter(self, A: np.ndarray, blocks) -> list:
        # hash=False: tokenising a large array costs more than sending it
        return [self.client.scatter(np.ascontiguousarray(A[a:b]), workers=[w], hash=False)
                for a, b, w in blocks]

    def _on_workers(self, X: np.ndarray, y: np.ndarray):
        """``(blocks, X futures, y futures)``: the rows on the workers, each array sent
        once for all the fits on it."""
        if self._last_X is None or self._last_X[0] is not X:
            blocks = self._blocks(len(X))
            self._last_X = (X, blocks, self._scatter(X, blocks))
            self._last_y = None
        _, blocks, xf = self._last_X
        if self._last_y is None or self._last_y[0] is not y:
            self._last_y = (y, self._scatter(y, blocks))
        return blocks, xf, self._last_y[1]

    def _rows(self, blocks, futures, rows, like: np.ndarray) -> object:
        """A dask array of ``rows`` (sorted, of the whole matrix; None: all) of the blocks
        ``futures``, each part cut where its block is (pinned: a part moved to another
        worker would leave a worker without data for xgboost.dask)."""
        import dask
        import dask.array as da

        parts = []
        for (a, b, w), fut in zip(blocks, futures):
            if rows is None:
                part, n = fut, b - a
            else:
                local = rows[(rows >= a) & (rows < b)] - a
                if not len(local):
                    continue
                part = self.client.submit(np.take, fut, local, axis=0, workers=[w],
                                          allow_other_workers=False)
                n = len(local)
            parts.append(da.from_delayed(dask.delayed(part), shape=(n,) + like.shape[1:],
                                         dtype=like.dtype))
        return da.concatenate(parts, axis=0)

    # -- fitting
    def _check(self, kind: str) -> None:
        _require_xgboost(kind)

    def _fit_rows(self, kind, task, dX, dy, *, seed: int, n_jobs: int):
        import xgboost as xgb
        from xgboost import dask as dxgb

        est = meta_model.make_estimator(kind, task, seed=seed, n_jobs=n_jobs)
        given = est.get_params()
        params = {k: v for k, v in given.items() if v is not None}
        cls = dxgb.DaskXGBClassifier if task == "classification" else dxgb.DaskXGBRegressor
        model = cls(**params)
        model.client = self.client
        # verbosity 0 (sent to the workers with the fit): no per-worker rank lines
        with xgb.config_context(verbosity=0):
            model.fit(dX, dy)
        # the same estimator class, parameters and pickle as a single-machine fit
        est.load_model(bytearray(model.get_booster().save_raw("ubj")))
        # load_model also copies the model's own values (base_score, booster) into the
        # wrapper's parameters; a single-machine fit keeps the constructor's. Plain
        # attributes: the booster, which holds what predicts, stays as trained.
        for k, v in given.items():
            setattr(est, k, v)
        return est

    def fit(self, kind, task, X, y, *, seed: int = 0, n_jobs: int = 1):
        self._check(kind)
        X, y = meta_model.training_arrays(X, y, task)
        if task == "classification" and np.unique(y).size < 2:
            raise ValueError("classification needs both classes in the training data")
        return self._fit_on(kind, task, X, y, None, seed=seed, n_jobs=n_jobs)

    def fit_folds(self, kind, task, X, y, folds, *, seed: int = 0, n_jobs: int = 1):
        self._check(kind)
        X, y = meta_model.training_arrays(X, y, task)
        for tr, _ in folds:
            yield self._fit_on(kind, task, X, y, np.sort(tr), seed=seed, n_jobs=n_jobs)

    def _fit_on(self, kind, task, X, y, rows, *, seed: int, n_jobs: int):
        blocks, xf, yf = self._on_workers(X, y)
        dX = self._rows(blocks, xf, rows, X)
        dy = self._rows(blocks, yf, rows, y)
        return self._fit_rows(kind, task, dX, dy, seed=seed, n_jobs=n_jobs)


def parse_scheduler(text: str) -> tuple[str, object]:
    """``("local", workers or None)``, ``("file", path)`` or ``("address", address)`` of a
    ``--scheduler`` value; ``ValueError`` naming the accepted forms otherwise."""
    text = text.strip()
    m = re.fullmatch(r"local(?::(\d+))?", text)
    if m:
        n = int(m.group(1)) if m.group(1) else None
        if n is not None and n < 1:
            raise ValueError(f"--scheduler {text}: a local cluster needs at least 1 worker")
        return "local", n
    if "://" in text:
        return "address", text
    if Path(text).is_file():
        return "file", Path(text)
    raise ValueError(f"--scheduler {text!r}: expected a Dask scheduler address "
                     "(tcp://HOST:PORT), an existing scheduler file, or local / local:N")


def check_scheduler(scheduler: str | None, kind: str) -> None:
    """``ValueError`` for a ``--scheduler`` value of the wrong form, or with an estimator
    kind that has no distributed fit (before any data is read)."""
    if scheduler is None:
        return
    parse_scheduler(scheduler)
    _require_xgboost(kind)


def _require_xgboost(kind: str) -> None:
    if kind != "xgboost":
        raise ValueError(f"--scheduler fits xgboost models only (xgboost.dask); kind {kind!r} "
                         "trains on this machine: leave out --scheduler")


@contextlib.contextmanager
def training_backend(scheduler: str | None, kind: str = "xgboost", *,
                     timeout: float | None = None) -> Iterator:
    """The backend of a run: :class:`LocalTraining` without ``scheduler``, else a
    :class:`DaskTraining` connected for the run (a ``local`` cluster is started and
    stopped). ``ValueError`` for a kind without a distributed fit or a bad address,
    ``OSError`` when the scheduler cannot be reached or has no worker within ``timeout``
    seconds (default: Dask's ``distributed.comm.timeouts.connect``, 30 s)."""
    if scheduler is None:
        yield LocalTraining()
        return
    check_scheduler(scheduler, kind)
    how, what = parse_scheduler(scheduler)
    import dask
    from dask.utils import parse_timedelta
    from distributed import Client, LocalCluster

    if timeout is None:
        timeout = parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"))

    with contextlib.ExitStack() as stack:
        try:
            if how == "local":
                # loopback only; no dashboard, and the scheduler's HTTP endpoint on a
                # free port (its default 8787 may be taken by another cluster)
                cluster = stack.enter_context(LocalCluster(
                    n_workers=what or os.cpu_count() or 1, threads_per_worker=1,
                    processes=True, host="127.0.0.1", dashboard_address=None,
                    scheduler_kwargs={"dashboard": False,
                                      "dashboard_address": "127.0.0.1:0"}))
                client = stack.enter_context(Client(cluster))
            elif how == "file":
                client = stack.enter_context(Client(scheduler_file=str(what), timeout=timeout))
            else:
                client = stack.enter_context(Client(what, timeout=timeout))
        except (OSError, TimeoutError) as exc:
            raise OSError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from None
        if not client.scheduler_info()["workers"]:
            try:
                client.wait_for_workers(1, timeout=timeout)
            except (OSError, TimeoutError):
                raise OSError(f"the Dask scheduler {scheduler} has no worker (waited "
                              f"{timeout:.0f} s)") from None
        yield DaskTraining(client, scheduler)


def add_scheduler_option(ap) -> None:
    """The trainers' ``--scheduler ADDRESS``."""
    ap.add_argument("--scheduler", default=None, metavar="ADDRESS", help=SCHEDULER_HELP)
