"""``lmd-eval``: the LMD evaluation report (markdown + PNG + summary.json) under ``--out``.

    lmd-eval --train data/perception/meta_train --test data/perception/meta_test --out out/lmd/eval

Meta models are fitted on the training data and evaluated on held-out sequences, and in
grouped cross validation over the training sequences. Compared, as in the paper (section
IV c), per estimator kind: the **score** baseline (a meta model on the detector score
alone), the **box features** baseline (the box's own features phi = x, y, z, l, w, h,
theta, score, class, eq. 3, score included) and **LMD** (all features of the mode).
Contents:

* Table I shape (main mode, every kind): accuracy, AUROC, AUPRC and R^2 per method, held
  out and grouped CV (mean ± std over folds);
* Table II shape (every proposal mode, ``--table2-kind``): accuracy, AUROC, R^2 per method;
* calibration: ECE / MCE (10 bins) of the detector score and of the meta classifiers;
  reliability diagrams (detector score vs LMD), copied to ``--docs-png``;
* true vs predicted IoU_BEV scatter; greedy forward selection curves (AUROC, R^2; stop at
  ``--greedy-max`` features or a gain below 5e-4); Pearson correlations of every feature
  with IoU_BEV (held-out data);
* annotation-error proposals (``annotation_review``) on the held-out data with injected
  label errors: precision@k of the LMD ranking vs the score ranking vs random.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core.jsonable import jsonable
from lidar_quality_core import metrics as M
from lidar_quality_core import report_plots as RP

from ..report import fmt, markdown_table
from . import annotation_review as AR
from .dataset import LmdDataset, Progress, add_source_args, load_from_args, settings_from_args
from .train import MODES, classification_metrics, regression_metrics

__all__ = ["BOX_FEATURES", "METHODS", "method_columns", "held_out", "cross_validated",
           "correlations", "greedy", "evaluate", "main"]

#: The paper's box-feature baseline: the box's own features phi (eq. 3), score included.
BOX_FEATURES = ("x", "y", "z", "l", "w", "h", "theta", "score", "class")
METHODS = {"score": "Score", "box": "Box features", "lmd": "LMD"}
KIND_LABEL = {"xgboost": "XGBoost", "gradient_boosting": "GB", "linear": "LogReg / RR",
              "random_forest": "RF", "mlp": "MLP"}


def method_columns(ds: LmdDataset, method: str):
    """Feature names of ``method`` (``None``: all of the dataset's)."""
    if method == "score":
        return ["score"]
    if method == "box":
        return list(BOX_FEATURES)
    if method == "lmd":
        return None
    raise ValueError(f"unknown method {method!r} (known: {list(METHODS)})")


def _X(ds, method):
    cols = method_columns(ds, method)
    return ds.X if cols is None else ds.columns(cols)


def held_out(train: LmdDataset, test: LmdDataset, kind: str, method: str, *, seed: int = 0,
             n_jobs: int = 1) -> dict:
    """Fit ``kind`` on ``train`` with ``method``'s features, evaluate on ``test``:
    ``{"classification": {...}, "regression": {...}, "confidence": (n,), "iou": (n,)}``."""
    Xtr, Xte = _X(train, method), _X(test, method)
    clf = meta_model.fit_estimator(kind, "classification", Xtr, train.tp.astype(float),
                                   seed=seed, n_jobs=n_jobs)
    reg = meta_model.fit_estimator(kind, "regression", Xtr, train.iou, seed=seed, n_jobs=n_jobs)
    conf = np.clip(meta_model.predict(clf, "classification", Xte), 0, 1)
    pred = np.clip(meta_model.predict(reg, "regression", Xte), 0, 1)
    return {"classification": classification_metrics(test.tp, conf),
            "regression": regression_metrics(test.iou, pred), "confidence": conf, "iou": pred}


def cross_validated(ds: LmdDataset, kind: str, method: str, *, n_folds: int, seed: int = 0,
                    n_jobs: int = 1) -> dict:
    """Grouped CV over the sequences: ``{task: {metric: (mean, std)}}`` (validation folds)."""
    X = _X(ds, method)
    out = {}
    for task, y in (("classification", ds.tp.astype(float)), ("regression", ds.iou)):
        r = meta_model.cross_validate(X, y, ds.group, task=task, kind=kind, n_folds=n_folds,
                                      seed=seed, n_jobs=n_jobs)
        out[task] = r.mean_std()["val"]
    return out


def correlations(ds: LmdDataset) -> list[tuple[str, float]]:
    """Pearson r of every feature with IoU_BEV, by |r| descending (NaN rows left out per
    feature; constant features: NaN, last)."""
    y = ds.iou
    out = []
    for j, name in enumerate(ds.feature_names):
        x = ds.X[:, j]
        ok = np.isfinite(x)
        xs, ys = x[ok], y[ok]
        r = (float(np.corrcoef(xs, ys)[0, 1]) if ok.sum() > 2 and xs.std() > 0 and ys.std() > 0
             else float("nan"))
        out.append((name, r))
    return sorted(out, key=lambda t: -abs(t[1]) if np.isfinite(t[1]) else np.inf)


def greedy(ds: LmdDataset, task: str, *, kind: str = "linear", max_features: int = 10,
           min_gain: float = 5e-4, n_folds: int = 3, max_rows: int = 8000, seed: int = 0,
           n_jobs: int = 1, candidates=None, progress: bool = False) -> dict:
    """Greedy forward selection (``meta_model.greedy_selection``) among ``candidates``
    (default: every feature) on at most ``max_rows`` rows (seeded sample; 0 = all)."""
    names = list(ds.feature_names if candidates is None else candidates)
    X = ds.columns(names)
    rows = np.arange(len(ds))
    if max_rows and len(ds) > max_rows:
        rows = np.sort(np.random.default_rng(seed).choice(len(ds), max_rows, replace=False))
    y = ds.tp.astype(float)[rows] if task == "classification" else ds.iou[rows]
    bar = Progress(f"  greedy selection ({task}, {kind})", max_features, progress)
    g = meta_model.greedy_selection(X[rows], y, names, ds.group[rows], task=task,
                                    kind=kind, n_folds=n_folds, max_features=max_features,
                                    min_gain=min_gain, seed=seed, n_jobs=n_jobs,
                                    progress=lambda *_: bar.update())
    bar.close()
    return {"selected": g.selected, "scores": g.scores, "metric": g.metric,
            "all_features": g.all_features_score, "kind": kind, "rows": int(len(rows)),
            "folds": n_folds, "candidates": len(names)}


def _bar_png(path, names, values, *, xlabel, title):
    fig = RP.figure(6.0, max(3.0, 0.22 * len(names) + 1.0))
    ax = fig.add_subplot(1, 1, 1)
    pos = np.arange(len(names))[::-1]
    ax.barh(pos, values, color=["#4c72b0" if v >= 0 else "#dd8452" for v in values])
    ax.set_yticks(pos)
    ax.set_yticklabels(names, fontsize=7)
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel(xlabel)
    ax.set_title(title, fontsize=10)
    return RP.save(fig, path)


def _strip(d):
    """Metrics without the prediction arrays (JSON)."""
    return {k: v for k, v in d.items() if k not in ("confidence", "iou")}


def evaluate(train_sets: dict, test_sets: dict, out: Path, *, mode: str = "threshold",
             kinds=meta_model.KINDS, cv_kinds=("xgboost",), table2_kind: str = "xgboost",
             cv_folds: int = 4, greedy_kind: str = "linear", greedy_max: int = 10,
             greedy_rows: int = 8000, greedy_features=None, review_k=(50, 100), thumbnails: int = 12,
             error_seed: int = 0, seed: int = 0, n_jobs: int = 1, docs_png: Path | None = None,
             progress: bool = True) -> dict:
    """Compute everything, write ``report.md``, the PNGs and ``summary.json`` to ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    tr, te = train_sets[mode], test_sets[mode]
    S: dict = {"mode": mode, "data": {"train": tr.summary(), "test": te.summary(),
                                      "train_sources": tr.groups, "test_sources": te.groups},
               "settings": tr.info.get("settings"), "class_aware": tr.class_aware}

    def log(msg):
        if progress:
            sys.stderr.write(msg + "\n")

    # --- Table I shape: every kind x method, held out ---------------------------------
    held: dict = {}
    preds: dict = {}
    bar = Progress(f"held-out fits ({mode})", len(kinds) * len(METHODS), progress)
    for kind in kinds:
        held[kind] = {}
        for method in METHODS:
            r = held_out(tr, te, kind, method, seed=seed, n_jobs=n_jobs)
            preds[(mode, kind, method)] = r
            held[kind][method] = _strip(r)
            bar.update(note=f"{kind}/{method}")
    bar.close()
    S["held_out"] = {mode: held}
    S["detector_score"] = {mode: classification_metrics(te.tp, te.score)}

    # --- Table II shape: every mode, one kind ------------------------------------------
    S["modes"] = {}
    other = [m for m in train_sets if m in test_sets]
    bar = Progress(f"per-mode fits ({table2_kind})", len(other) * len(METHODS), progress)
    for m in other:
        S["modes"][m] = {}
        for method in METHODS:
            key = (m, table2_kind, method)
            if key not in preds:
                preds[key] = held_out(train_sets[m], test_sets[m], table2_kind, method,
                                      seed=seed, n_jobs=n_jobs)
            S["modes"][m][method] = _strip(preds[key])
            bar.update(note=f"{m}/{method}")
        S["detector_score"][m] = classification_metrics(test_sets[m].tp, test_sets[m].score)
    bar.close()

    # --- grouped CV over the training sequences ----------------------------------------
    S["cv"] = {}
    bar = Progress(f"grouped CV ({cv_folds} folds)", len(cv_kinds) * len(METHODS), progress)
    for kind in cv_kinds:
        S["cv"][kind] = {}
        for method in METHODS:
            S["cv"][kind][method] = cross_validated(tr, kind, method, n_folds=cv_folds,
                                                    seed=seed, n_jobs=n_jobs)
            bar.update(note=f"{kind}/{method}")
    bar.close()

    # --- calibration, scatter, correlations ----------------------------------------------
    main_kind = table2_kind if table2_kind in kinds else kinds[0]
    lmd = preds[(mode, main_kind, "lmd")]
    calib = {"detector score": M.reliability_diagram(te.tp.astype(float), te.score)}
    for kind in kinds:
        for method in METHODS:
            rd = M.reliability_diagram(te.tp.astype(float), preds[(mode, kind, method)]["confidence"])
            calib[f"{METHODS[method]} ({KIND_LABEL[kind]})"] = rd
    S["calibration"] = {k: {"ece": v.ece, "mce": v.mce} for k, v in calib.items()}
    pngs = {}
    pngs["reliability"] = RP.reliability_png(
        out / f"reliability_{mode}.png",
        {"detector score": (te.tp, te.score), f"LMD ({KIND_LABEL[main_kind]})": (te.tp, lmd["confidence"])},
        title=f"Held-out reliability, {mode} mode")
    pngs["reliability_baselines"] = RP.reliability_png(
        out / f"reliability_baselines_{mode}.png",
        {f"{METHODS[m]} ({KIND_LABEL[main_kind]})": (te.tp, preds[(mode, main_kind, m)]["confidence"])
         for m in METHODS}, title="Meta classifiers by feature set")
    pngs["scatter"] = RP.scatter_png(out / f"iou_scatter_{mode}.png", te.iou, lmd["iou"],
                                     xlabel="true IoU_BEV", ylabel="predicted IoU_BEV",
                                     title=f"LMD ({KIND_LABEL[main_kind]})")
    pngs["scatter_score"] = RP.scatter_png(
        out / f"iou_scatter_score_{mode}.png", te.iou, preds[(mode, main_kind, "score")]["iou"],
        xlabel="true IoU_BEV", ylabel="predicted IoU_BEV",
        title=f"Score baseline ({KIND_LABEL[main_kind]})")
    corr = correlations(te)
    S["correlations"] = corr
    top = [c for c in corr if np.isfinite(c[1])][:25]
    pngs["correlations"] = _bar_png(out / f"correlations_{mode}.png", [c[0] for c in top],
                                    [c[1] for c in top], xlabel="Pearson r with IoU_BEV",
                                    title="Strongest feature correlations (held out)")
    if docs_png is not None:
        Path(docs_png).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(pngs["reliability"], docs_png)

    # --- greedy selection ------------------------------------------------------------------
    S["greedy"] = {}
    if greedy_max > 0:
        for task, label in (("classification", "AUROC"), ("regression", "R²")):
            g = greedy(tr, task, kind=greedy_kind, max_features=greedy_max, n_folds=3,
                       max_rows=greedy_rows, seed=seed, n_jobs=n_jobs,
                       candidates=greedy_features, progress=progress)
            S["greedy"][task] = g
            pngs[f"greedy_{task}"] = RP.curve_png(
                out / f"greedy_{task}_{mode}.png", [f"+{n}" for n in g["selected"]],
                g["scores"], ylabel=f"grouped CV {label}",
                title=f"Greedy selection ({KIND_LABEL[greedy_kind]}); all features: "
                      f"{g['all_features']:.4f}")

    # --- annotation-error proposals --------------------------------------------------------
    errors = AR.inject_errors(te, seed=error_seed)
    res = AR.review(te, lmd["confidence"], lmd["iou"], errors=errors, ks=review_k, seed=error_seed)
    rdir = out / "annotation_review"
    AR.export(te, res, lmd["confidence"], lmd["iou"], rdir, k=max(review_k))
    AR.export(te, res, lmd["confidence"], lmd["iou"], rdir, k=max(review_k), ranking="score")
    if thumbnails:
        paths = AR.thumbnails(te, res, lmd["confidence"], lmd["iou"], rdir, k=thumbnails,
                              errors=errors)
        if paths:
            pngs["review_sheet"] = paths[-1]
    S["annotation_review"] = {**AR.summary(res, errors), "seed": error_seed,
                              "model": f"the LMD meta models ({KIND_LABEL[main_kind]}, {mode} mode)"}

    # --- acceptance (issue 5) ---------------------------------------------------------------
    acc = {}
    for m in S["modes"]:
        r = S["modes"][m]
        auc = {k: r[k]["classification"]["auroc"] for k in METHODS}
        ece_lmd = r["lmd"]["classification"]["ece"]
        ece_score = S["detector_score"][m]["ece"]
        acc[m] = {"kind": table2_kind, "auroc": auc,
                  "detector_score_auroc": S["detector_score"][m]["auroc"],
                  "lmd_auroc_above_score": bool(auc["lmd"] > max(auc["score"],
                                                                 S["detector_score"][m]["auroc"])),
                  "lmd_auroc_above_box": bool(auc["lmd"] > auc["box"]),
                  "ece_lmd": ece_lmd, "ece_detector_score": ece_score,
                  "ece_below_score": bool(ece_lmd < ece_score),
                  "r2_lmd": r["lmd"]["regression"]["r2"]}
    S["acceptance"] = acc
    S["seconds"] = time.monotonic() - t_start
    S["pngs"] = {k: Path(v).name if Path(v).parent == out else str(Path(v).relative_to(out))
                 for k, v in pngs.items()}
    (out / "summary.json").write_text(json.dumps(jsonable(S), indent=1) + "\n")
    (out / "report.md").write_text(_report(S, kinds, cv_kinds, table2_kind, main_kind, cv_folds))
    log(f"report: {out / 'report.md'} ({S['seconds']:.0f} s)")
    return S


# ---------------------------------------------------------------------------- report
def _report(S, kinds, cv_kinds, t2kind, main_kind, cv_folds) -> str:
    mode = S["mode"]
    d = S["data"]
    L = [f"# LMD evaluation ({mode} mode)", "",
         f"Training: {d['train']['frames']} frames, {d['train']['boxes']} boxes (TP rate "
         f"{fmt(d['train']['tp_rate'])}) from {d['train']['groups']} sequences; held out: "
         f"{d['test']['frames']} frames, {d['test']['boxes']} boxes (TP rate "
         f"{fmt(d['test']['tp_rate'])}) from {d['test']['groups']} sequences. Target: "
         f"IoU_BEV with the best ground-truth box ({'same class' if S['class_aware'] else 'any class'}); "
         "TP iff IoU_BEV >= 0.5. Methods: **Score** = meta model on the detector score only; "
         "**Box features** = on the box's own features x, y, z, l, w, h, theta, score, class "
         "(the paper's phi, eq. 3); **LMD** = all features of the mode. Meta models are fitted "
         "on the training sequences.", ""]
    H = S["held_out"][mode]
    kl = [KIND_LABEL[k] for k in kinds]
    for title, task, metric in (("Accuracy", "classification", "accuracy"),
                                ("AUROC", "classification", "auroc"),
                                ("AUPRC", "classification", "auprc"),
                                ("R²", "regression", "r2")):
        L += [f"### Held-out {title} (Table I shape)", ""]
        rows = [[METHODS[m]] + [H[k][m][task][metric] for k in kinds] for m in METHODS]
        L.append(markdown_table(["method"] + kl, rows, digits=4))
    ds = S["detector_score"][mode]
    L += [f"Detector score itself (no meta model): accuracy {fmt(ds['accuracy'], 4)}, AUROC "
          f"{fmt(ds['auroc'], 4)}, AUPRC {fmt(ds['auprc'], 4)}, ECE {fmt(ds['ece'], 4)}, "
          f"MCE {fmt(ds['mce'], 4)}.", ""]

    L += [f"## Proposal modes (Table II shape, {KIND_LABEL[t2kind]}, held out)", ""]
    rows = []
    for m, r in S["modes"].items():
        rows.append([m] + [r[x]["classification"]["accuracy"] for x in METHODS]
                    + [r[x]["classification"]["auroc"] for x in METHODS]
                    + [r[x]["regression"]["r2"] for x in METHODS])
    L.append(markdown_table(["mode", "acc Score", "acc Box", "acc LMD", "AUROC Score",
                             "AUROC Box", "AUROC LMD", "R² Score", "R² Box", "R² LMD"], rows,
                            digits=4))
    L += ["Mode `none` has no proposal features: its LMD set is the 17 own-box features.", ""]

    L += [f"## Grouped {cv_folds}-fold cross validation over the training sequences", "",
          "Mean ± std over the validation folds (each fold holds out whole sequences).", ""]
    for kind in cv_kinds:
        C = S["cv"][kind]
        rows = [[METHODS[m], tuple(C[m]["classification"]["accuracy"]),
                 tuple(C[m]["classification"]["auroc"]), tuple(C[m]["classification"]["auprc"]),
                 tuple(C[m]["regression"]["r2"])] for m in METHODS]
        L += [f"**{KIND_LABEL[kind]}**", "",
              markdown_table(["method", "accuracy", "AUROC", "AUPRC", "R²"], rows, digits=4)]

    L += ["## Calibration (held out, 10 equal-width bins)", ""]
    L.append(markdown_table(["confidence", "ECE", "MCE"],
                            [[k, v["ece"], v["mce"]] for k, v in S["calibration"].items()],
                            digits=4))
    P = S["pngs"]
    L += [f"![reliability]({P['reliability']})", "",
          f"![reliability by feature set]({P['reliability_baselines']})", "",
          "## Meta regression: true vs predicted IoU_BEV", "",
          f"![scatter]({P['scatter']}) ![scatter score]({P['scatter_score']})", ""]
    if S["greedy"]:
        L += ["## Greedy forward feature selection", ""]
        for task, g in S["greedy"].items():
            L += [f"**{task}** ({KIND_LABEL[g['kind']]}, grouped {g['folds']}-fold CV {g['metric']} "
                  f"on {g['rows']} training rows, {g['candidates']} candidate features; all of "
                  f"them: {fmt(g['all_features'], 4)})", ""]
            L.append(markdown_table(["step", "feature added", g["metric"]],
                                    [[i + 1, n, s] for i, (n, s) in
                                     enumerate(zip(g["selected"], g["scores"]))], digits=4))
            L += [f"![greedy {task}]({P[f'greedy_{task}']})", ""]
    L += ["## Feature correlations with IoU_BEV (held out, Pearson)", ""]
    top = [c for c in S["correlations"] if c[1] is not None and np.isfinite(c[1])][:15]
    L.append(markdown_table(["feature", "r"], [[n, r] for n, r in top], digits=4))
    L += [f"![correlations]({P['correlations']})", ""]

    R = S["annotation_review"]
    L += ["## Annotation-error proposals", "",
          f"Label errors injected into the held-out ground truth (`lidar_sim.annotation_errors`, "
          f"seed {R['seed']}, boxes with >= 1 point): "
          + ", ".join(f"{k} {v}" for k, v in R["errors_injected"].items())
          + f" ({R['corrupted_objects']} objects). FPs against the corrupted labels: "
          f"{R['fp_total']}, ranked by the predicted IoU of {R['model']} (`lmd_iou`), by its "
          "confidence, by the detector score and at random. Hit rules: **caused** = "
          f"{R['hit_rules']['caused']}; **near** = {R['hit_rules']['near']}.", ""]
    ks = list(next(iter(next(iter(R["precision_at_k"].values())).values())).keys())
    rows = []
    for name, d in R["precision_at_k"].items():
        rows.append([name] + [d[rule][k] for rule in ("caused", "near") for k in ks])
    rows.append(["random (expected)"] + [R["expected_random_precision"][rule]
                                         for rule in ("caused", "near") for _ in ks])
    L.append(markdown_table(["ranking"] + [f"{rule} P@{k}" for rule in ("caused", "near")
                                           for k in ks], rows, digits=2))
    L += ["Exports: `annotation_review/proposals_lmd_iou.csv|json`, "
          "`annotation_review/proposals_score.csv|json`; thumbnails in "
          "`annotation_review/thumbnails/`.", ""]
    if "review_sheet" in P:
        L += [f"![proposals]({P['review_sheet']})", ""]

    L += ["## Acceptance (issue 5)", ""]
    rows = [[m, a["auroc"]["lmd"], a["auroc"]["box"], a["auroc"]["score"],
             a["detector_score_auroc"], a["ece_lmd"], a["ece_detector_score"], a["r2_lmd"],
             "yes" if a["lmd_auroc_above_score"] and a["lmd_auroc_above_box"]
             and a["ece_below_score"] else "no"] for m, a in S["acceptance"].items()]
    L.append(markdown_table(["mode", "AUROC LMD", "AUROC Box", "AUROC Score (model)",
                             "AUROC detector score", "ECE LMD", "ECE detector score",
                             "R² LMD", "met"], rows, digits=4))
    L.append(f"\n_{S['seconds']:.0f} s._\n")
    return "\n".join(L)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lmd-eval", description=__doc__.split("\n\n")[0])
    add_source_args(ap)
    ap.add_argument("--out", type=Path, default=Path("out/lmd/eval"))
    ap.add_argument("--mode", choices=MODES, default="threshold", help="mode of Table I etc.")
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                    help="modes of the Table II comparison")
    ap.add_argument("--kinds", nargs="+", choices=meta_model.KINDS, default=list(meta_model.KINDS))
    ap.add_argument("--cv-kinds", nargs="*", choices=meta_model.KINDS, default=["xgboost"])
    ap.add_argument("--table2-kind", choices=meta_model.KINDS, default="xgboost")
    ap.add_argument("--cv-folds", type=int, default=4)
    ap.add_argument("--greedy-kind", choices=meta_model.KINDS, default="linear")
    ap.add_argument("--greedy-max", type=int, default=10, help="0: no selection")
    ap.add_argument("--greedy-rows", type=int, default=8000, help="0: all training rows")
    ap.add_argument("--greedy-features", nargs="+", default=None,
                    help="candidate features of the selection (default: all)")
    ap.add_argument("--review-k", type=int, nargs="+", default=[50, 100])
    ap.add_argument("--thumbnails", type=int, default=12)
    ap.add_argument("--error-seed", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--docs-png", type=Path, default=None,
                    help="copy the reliability diagram here (e.g. docs/lmd_reliability.png)")
    args = ap.parse_args(argv)
    modes = list(dict.fromkeys([args.mode] + args.modes))
    settings = settings_from_args(args, modes)
    train_sets = load_from_args(args, settings, "train")
    test_sets = load_from_args(args, settings, "test")
    if test_sets is None:
        raise SystemExit("lmd-eval needs held-out data (--test, or --kitti-test-frames)")
    S = evaluate(train_sets, test_sets, args.out, mode=args.mode, kinds=args.kinds,
                 cv_kinds=args.cv_kinds, table2_kind=args.table2_kind, cv_folds=args.cv_folds,
                 greedy_kind=args.greedy_kind, greedy_max=args.greedy_max,
                 greedy_rows=args.greedy_rows, greedy_features=args.greedy_features,
                 review_k=args.review_k,
                 thumbnails=args.thumbnails, error_seed=args.error_seed, seed=args.seed,
                 n_jobs=args.jobs, docs_png=args.docs_png, progress=not args.quiet)
    for m, a in S["acceptance"].items():
        print(f"{m}: AUROC LMD {a['auroc']['lmd']:.4f} / box {a['auroc']['box']:.4f} / score "
              f"{a['auroc']['score']:.4f}; ECE LMD {a['ece_lmd']:.4f} vs score "
              f"{a['ece_detector_score']:.4f}; R^2 {a['r2_lmd']:.4f}")
    print(f"report: {args.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
