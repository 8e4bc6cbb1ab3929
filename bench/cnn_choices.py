"""The CNN descriptor's unstated values, measured: triplet margin, optimiser,
channel widths and hidden width, one at a time against the default, scored on held-out places.

The semi-dense paper (Sec. 3.3.2, 4.2) fixes the input, the layer types, the 512-d output, the
batch of 25 and SGD; it gives no margin, no learning rate, no channel counts and no hidden width.
``mapkit.learning.train.TrainConfig`` and ``mapkit.places.cnn.CnnConfig`` chose margin 0.5, Adam
at 1e-3, convolutions of 8 and 16 channels and a 512-wide hidden layer. This script trains each
variant below on one workspace's triplet dataset at one fixed budget and scores it with
``mapkit eval places`` (method ``cnn``) on the held-out places of that dataset's test tiles, on
the session pairs the demo's place-recognition stage picks (``mapkit.pipelines.demo.places_pairs``).
M2DP is scored once on the same queries as the hand-crafted reference.

Variants (each differs from ``default`` in one value)::

    margin     margin-0.25, margin-1.0                    (default 0.5)
    optimizer  sgd-0.01, sgd-0.1 (momentum 0.9)           (default adam, lr 1e-3)
    widths     conv-4-8, conv-16-32                       (default conv 8 / 16)
    hidden     hidden-256                                 (default 512)

Every run uses seed 0 first; then (unless ``--no-second-seed``) the default and the best variant
of each group (by mean held-out AUC) are trained again with seed 1, so that a difference can be
told from the spread between seeds (initial weights, triplet draw, batch order, hard-negative
draws all follow the seed). More seeds for some variants: run again with ``--variants ... --seeds 2,3
--no-second-seed``; the tables always list every finished run of the output folder, so a folder
holds one budget on one dataset (a run of another budget there is left out, with a note).

Per run: mean held-out AUC of the CNN over the pairs and per pair, the mean over all places, the
test-split triplet accuracy of the training run's last epoch, training wall and CPU time and their
ratio to the default's (seed 0) in the same run. Output folder::

    runs/<variant>-s<seed>/      the trained model (mapkit train's folder; a finished run is not trained again)
    places/<variant>-s<seed>/    mapkit eval places of that model (reused when it scored the same model on
                                 the same pairs)
    places/m2dp/                 the reference
    cnn_choices.json             every figure; cnn_choices.md the tables

Run from the repository root, one training at a time (2 torch threads), niced on a shared machine::

    nice -n 5 python3 bench/cnn_choices.py WS TOWN --out DIR
    nice -n 5 python3 bench/cnn_choices.py WS TOWN --out DIR --variants default,margin-1.0 --seeds 0,1 --no-second-seed

``WS`` is an aligned workspace with a triplet dataset (``WS/triplets`` or ``--triplets``), ``TOWN``
its synthetic town (ground truth of the places). The hard negatives of training use the dataset's
own ``negative_min_distance_m``, so that training and dataset agree on what a non-match is.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from mapkit.core.errors import MapkitError
from mapkit.core.runio import read_timings

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import report  # noqa: E402 (after sys.path points at this checkout)

#: each variant's TrainConfig overrides (the default is TrainConfig's own values)
VARIANTS: dict[str, dict] = {
    "default": {},
    "margin-0.25": {"margin": 0.25},
    "margin-1.0": {"margin": 1.0},
    "sgd-0.01": {"optimizer": "sgd", "lr": 0.01, "momentum": 0.9},
    "sgd-0.1": {"optimizer": "sgd", "lr": 0.1, "momentum": 0.9},
    "conv-4-8": {"model": {"conv1_channels": 4, "conv2_channels": 8}},
    "conv-16-32": {"model": {"conv1_channels": 16, "conv2_channels": 32}},
    "hidden-256": {"model": {"hidden": 256}},
}
#: variants that change the same value: the best of each gets a second seed
GROUPS: dict[str, list[str]] = {
    "margin": ["margin-0.25", "margin-1.0"],
    "optimizer": ["sgd-0.01", "sgd-0.1"],
    "widths": ["conv-4-8", "conv-16-32"],
    "hidden": ["hidden-256"],
}
#: the demo's training budget (mapkit.pipelines.demo.CNN_DEMO_BUDGET)
DEFAULT_BUDGET = "triplet_set=2000,epochs=5"


def parse_budget(text: str) -> dict:
    """``"triplet_set=2000,epochs=5"`` -> ``{"triplet_set": 2000, "epochs": 5}`` (ints, else floats, else strings)."""
    out: dict = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        if "=" not in item:
            raise SystemExit(f"--budget: {item!r} is not key=value")
        k, v = (s.strip() for s in item.split("=", 1))
        for cast in (int, float):
            try:
                out[k] = cast(v)
                break
            except ValueError:
                continue
        else:
            out[k] = v
    return out


def demo_pairs(ws, town: Path) -> list[tuple[str, str]]:
    """The (database, query) pairs of the demo's place-recognition stage."""
    from mapkit.evaluation.truth import town_sessions
    from mapkit.pipelines.demo import _map_points, places_pairs

    return places_pairs(town_sessions(town), _map_points(ws))


def dataset_negative_distance(triplets: Path) -> float:
    """The triplet dataset's ``negative_min_distance_m`` (its config.yaml)."""
    from mapkit.core.config import load_config
    from mapkit.places.triplets import TripletConfig

    return load_config(TripletConfig, triplets / "config.yaml").negative_min_distance_m


def _same_eval(folder: Path, pairs: list[tuple[str, str]], methods: list[str], fingerprint: dict | None) -> dict | None:
    """The results in ``folder`` when they scored ``methods`` on ``pairs`` (with the model of ``fingerprint``)."""
    f = folder / "places.json"
    if not f.is_file():
        return None
    r = json.loads(f.read_text())
    if r.get("methods") != methods or [(p["database"], p["query"]) for p in r.get("pairs", [])] != [
        tuple(p) for p in pairs
    ]:
        return None
    if fingerprint is not None and (r.get("cnn_model") or {}).get("onnx_sha256") != fingerprint["onnx_sha256"]:
        return None
    return r


def evaluate(
    ws: Path,
    town: Path,
    triplets: Path,
    pairs: list[tuple[str, str]],
    method: str,
    out: Path,
    model: Path | None = None,
) -> dict:
    """``mapkit eval places`` of one method into ``out`` (reused when already there), held out by ``triplets``'
    tiles."""
    from mapkit.evaluation.places import evaluate_places

    fp = None
    if model is not None:
        from mapkit.places.cnn import model_fingerprint

        fp = model_fingerprint(model)
    done = _same_eval(out, pairs, [method], fp)
    if done is not None:
        return done
    ov: dict = {"split": "triplets", "triplets_dir": str(triplets)}
    if model is not None:
        ov["structure"] = {"cnn_model": str(model)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pairs without held-out queries are reported in the figures
        return evaluate_places(ws, pairs, [method], out=out, truth=town, overrides=ov)


def auc_figures(r: dict, method: str) -> dict:
    """Held-out AUC per pair and their mean (pairs with a defined AUC), the all-places mean, held-out queries."""
    per, allp, queries = {}, {}, {}
    for p in r["pairs"]:
        key = f"{p['database']}:{p['query']}"
        per[key] = p["methods"].get(method, {}).get("auc")
        allp[key] = p["all_places"]["methods"].get(method, {}).get("auc")
        queries[key] = p.get("held_out_queries")

    def mean(d):
        v = [x for x in d.values() if x is not None]
        return float(np.mean(v)) if v else None

    return {
        "auc_mean": mean(per),
        "auc_per_pair": per,
        "auc_all_places_mean": mean(allp),
        "auc_all_places_per_pair": allp,
        "held_out_queries": queries,
    }


def run_variant(
    name: str,
    seed: int,
    ws: Path,
    town: Path,
    triplets: Path,
    pairs: list[tuple[str, str]],
    out: Path,
    budget: dict,
    neg_m: float,
    threads: int,
) -> dict:
    """Train one variant (resumed or skipped when done) and score it; returns its row of figures."""
    from mapkit.core.config import deep_merge
    from mapkit.learning.train import train_cnn

    tag = f"{name}-s{seed}"
    overrides = deep_merge(
        deep_merge(dict(budget), VARIANTS[name]), {"seed": seed, "threads": threads, "negative_min_distance_m": neg_m}
    )
    t0 = time.perf_counter()
    model = train_cnn(triplets, out / "runs" / tag, overrides=overrides)
    call_s = time.perf_counter() - t0
    m = {**json.loads((model / "metrics.json").read_text()), **read_timings(model)}
    t1 = time.perf_counter()
    r = evaluate(ws, town, triplets, pairs, "cnn", out / "places" / tag, model)
    eval_s = time.perf_counter() - t1
    ep = json.loads((model / "metrics.json").read_text())["epochs"]
    row = {
        "variant": name,
        "seed": seed,
        "overrides": VARIANTS[name],
        **auc_figures(r, "cnn"),
        "test_accuracy": m["final"].get("test_accuracy"),
        "test_margin_mean": m["final"].get("test_margin_mean"),
        "final_loss": m["final"].get("loss"),
        "train_wall_s": m.get("wall_s_training"),
        "train_cpu_s": float(sum(e.get("train_cpu_s", 0.0) for e in m["epochs"])),
        "triplets_per_s": m.get("triplets_per_s_mean"),
        "triplet_set": m.get("triplet_set"),
        "epochs": len(ep),
        "this_call_train_s": call_s,
        "this_call_eval_s": eval_s,
        "model": str(model),
        "places": str(out / "places" / tag),
    }
    print(
        f"[cnn_choices] {tag}: held-out mean AUC {_f(row['auc_mean'])}, test accuracy {_f(row['test_accuracy'])}, "
        f"training {row['train_wall_s']:.0f} s wall",
        flush=True,
    )
    return row


def finished_runs(out: Path) -> list[tuple[str, int]]:
    """(variant, seed) of every finished model under ``out/runs`` named ``<variant>-s<seed>``."""
    found = []
    for d in sorted((out / "runs").glob("*-s*")):
        name, _, seed = d.name.rpartition("-s")
        if name in VARIANTS and seed.isdigit() and (d / "model.onnx").is_file() and (d / "metrics.json").is_file():
            found.append((name, int(seed)))
    return found


def _f(x, nd: int = 3) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"


def best_of_groups(rows: list[dict]) -> dict[str, str | None]:
    """The variant of each group with the highest seed-0 mean held-out AUC (None when none was run or scored)."""
    s0 = {r["variant"]: r["auc_mean"] for r in rows if r["seed"] == 0 and r["auc_mean"] is not None}
    out = {}
    for g, names in GROUPS.items():
        have = [n for n in names if n in s0]
        out[g] = max(have, key=lambda n: s0[n]) if have else None
    return out


def summarise(rows: list[dict]) -> list[dict]:
    """Per variant: mean over its seeds of the held-out AUC, each seed's, the spread, accuracy, time."""
    base = next((r for r in rows if r["variant"] == "default" and r["seed"] == 0), None)
    out = []
    for name in VARIANTS:
        rs = [r for r in rows if r["variant"] == name]
        if not rs:
            continue
        a = [r["auc_mean"] for r in rs if r["auc_mean"] is not None]
        out.append(
            {
                "variant": name,
                "seeds": len(rs),
                "auc_mean": float(np.mean(a)) if a else None,
                "auc_by_seed": " / ".join(_f(r["auc_mean"]) for r in rs),
                "spread": float(max(a) - min(a)) if len(a) > 1 else None,
                "sd": float(np.std(a, ddof=1)) if len(a) > 1 else None,
                "auc_all_places": float(
                    np.mean([r["auc_all_places_mean"] for r in rs if r["auc_all_places_mean"] is not None])
                )
                if any(r["auc_all_places_mean"] is not None for r in rs)
                else None,
                "test_accuracy": float(np.mean([r["test_accuracy"] for r in rs if r["test_accuracy"] is not None]))
                if any(r["test_accuracy"] is not None for r in rs)
                else None,
                "train_wall_s": float(np.mean([r["train_wall_s"] for r in rs])),
                "train_cpu_s": float(np.mean([r["train_cpu_s"] for r in rs])),
                "cpu_ratio_to_default": (float(np.mean([r["train_cpu_s"] for r in rs])) / base["train_cpu_s"])
                if base and base["train_cpu_s"]
                else None,
            }
        )
    return out


def markdown(result: dict) -> str:
    """The tables of cnn_choices.md."""
    pairs = [f"{d}:{q}" for d, q in result["pairs"]]
    lines = [
        f"# CNN choices on {result['workspace']}",
        "",
        f"Triplets {result['triplets']} (negatives beyond {result['negative_min_distance_m']:g} m), budget "
        f"{result['budget']}, pairs as the demo picks them; held-out places of the dataset's test tiles.",
        "",
        "| variant | seed | "
        + " | ".join(pairs)
        + " | mean held-out AUC | all places | test accuracy | train wall s | train CPU s |",
        "|---|---|" + "---|" * len(pairs) + "---|---|---|---|---|",
    ]
    ref = result.get("reference")
    if ref:
        lines.append(
            f"| {ref['method']} (reference) | - | "
            + " | ".join(_f(ref["auc_per_pair"].get(p)) for p in pairs)
            + f" | {_f(ref['auc_mean'])} | {_f(ref['auc_all_places_mean'])} | - | - | - |"
        )
    for r in result["runs"]:
        lines.append(
            f"| {r['variant']} | {r['seed']} | "
            + " | ".join(_f(r["auc_per_pair"].get(p)) for p in pairs)
            + f" | {_f(r['auc_mean'])} | {_f(r['auc_all_places_mean'])} | {_f(r['test_accuracy'])} | "
            f"{r['train_wall_s']:.0f} | {r['train_cpu_s']:.0f} |"
        )
    if result["runs"]:
        q = result["runs"][0]["held_out_queries"]
        lines += ["", "Held-out queries per pair: " + ", ".join(f"{p} {q.get(p)}" for p in pairs)]
    lines += [
        "",
        "| variant | seeds | mean held-out AUC | by seed | spread | sd | all places | test accuracy | train wall s | "
        "train CPU s | CPU / default |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in result["summary"]:
        lines.append(
            f"| {s['variant']} | {s['seeds']} | {_f(s['auc_mean'])} | {s['auc_by_seed']} | {_f(s['spread'])} | "
            f"{_f(s['sd'])} | {_f(s['auc_all_places'])} | {_f(s['test_accuracy'])} | {s['train_wall_s']:.0f} | "
            f"{s['train_cpu_s']:.0f} | {_f(s['cpu_ratio_to_default'], 2)} |"
        )
    lines += ["", "Best of each group (seed 0): " + ", ".join(f"{g} {v}" for g, v in result["best_of_groups"].items())]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("workspace", type=Path, help="aligned workspace (mapkit demo's WORKSPACE)")
    ap.add_argument("town", type=Path, help="its synthetic town (ground truth)")
    ap.add_argument("--out", type=Path, required=True, help="output folder (models, evaluations, cnn_choices.json)")
    ap.add_argument(
        "--triplets", type=Path, default=None, help="triplet dataset to train on and split by (default WS/triplets)"
    )
    ap.add_argument(
        "--budget",
        default=DEFAULT_BUDGET,
        help=f"TrainConfig overrides of every run (default {DEFAULT_BUDGET}, the demo's)",
    )
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of: {', '.join(VARIANTS)}")
    ap.add_argument("--seeds", default="0", help="seeds every listed variant is trained with (comma-separated)")
    ap.add_argument(
        "--no-second-seed", action="store_true", help="do not train the default and each group's best again with seed 1"
    )
    ap.add_argument("--pairs", default=None, help="db:query pairs, comma-separated (default: the demo's places_pairs)")
    ap.add_argument("--reference", default="m2dp", help="structure method scored once beside the CNN ('' for none)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads per training")
    a = ap.parse_args(argv)

    from mapkit.core.runio import atomic_write_text, write_json
    from mapkit.core.workspace import Workspace

    ws = Workspace(a.workspace)
    triplets = (a.triplets or ws.triplets_dir).resolve()
    if not (triplets / "manifest.json").is_file():
        raise SystemExit(f"{triplets}: no triplet dataset (mapkit triplets)")
    names = [n.strip() for n in a.variants.split(",") if n.strip()]
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise SystemExit(f"--variants: unknown {unknown}; known: {', '.join(VARIANTS)}")
    seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
    pairs = [tuple(p.split(":", 1)) for p in a.pairs.split(",")] if a.pairs else demo_pairs(ws, a.town)
    if not pairs:
        raise SystemExit("no session pair to score")
    budget = parse_budget(a.budget)
    neg_m = dataset_negative_distance(triplets)
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    print(f"[cnn_choices] pairs {pairs}; budget {budget}; triplets {triplets} (negatives > {neg_m:g} m)", flush=True)

    result: dict = {
        "workspace": str(ws.root),
        "town": str(a.town),
        "triplets": str(triplets),
        "negative_min_distance_m": neg_m,
        "budget": budget,
        "pairs": [list(p) for p in pairs],
        "runs": [],
        "reference": None,
    }
    if a.reference:
        r = evaluate(ws.root, a.town, triplets, pairs, a.reference, out / "places" / a.reference)
        result["reference"] = {"method": a.reference, **auc_figures(r, a.reference)}
        print(f"[cnn_choices] {a.reference}: held-out mean AUC {_f(result['reference']['auc_mean'])}", flush=True)

    def save():
        result["best_of_groups"] = best_of_groups(result["runs"])
        result["summary"] = summarise(result["runs"])
        write_json(out / "cnn_choices.json", result)
        atomic_write_text(out / "cnn_choices.md", markdown(result))

    plan = [(n, s) for s in seeds for n in names]
    for n, s in plan:
        result["runs"].append(run_variant(n, s, ws.root, a.town, triplets, pairs, out, budget, neg_m, a.threads))
        save()
    if not a.no_second_seed:
        done = {(r["variant"], r["seed"]) for r in result["runs"]}
        again = ["default"] + [v for v in best_of_groups(result["runs"]).values() if v is not None]
        for n in again:
            if n in names and (n, 1) not in done:
                result["runs"].append(
                    run_variant(n, 1, ws.root, a.town, triplets, pairs, out, budget, neg_m, a.threads)
                )
                save()
    # every other run finished earlier in this folder (other seeds, other variants): in the tables too
    done = {(r["variant"], r["seed"]) for r in result["runs"]}
    for n, s in finished_runs(out):
        if (n, s) not in done:
            try:
                result["runs"].append(
                    run_variant(n, s, ws.root, a.town, triplets, pairs, out, budget, neg_m, a.threads)
                )
            except MapkitError as exc:  # trained with another budget or dataset: not comparable
                print(f"[cnn_choices] {n}-s{s} left out: {exc}", flush=True)
    result["runs"].sort(key=lambda r: (list(VARIANTS).index(r["variant"]), r["seed"]))
    save()

    rows = [
        {
            k: s[k]
            for k in (
                "variant",
                "seeds",
                "auc_mean",
                "auc_by_seed",
                "spread",
                "sd",
                "auc_all_places",
                "test_accuracy",
                "train_wall_s",
                "train_cpu_s",
                "cpu_ratio_to_default",
            )
        }
        for s in result["summary"]
    ]
    ref = result["reference"]
    report(
        "CNN choices: held-out place recognition per variant",
        rows,
        ratio_note=(f"{ref['method']} on the same held-out queries: mean AUC {_f(ref['auc_mean'])}. " if ref else "")
        + "cpu_ratio_to_default: training CPU time against the default (seed 0) in this run. Tables: "
        + str(out / "cnn_choices.md"),
    )
    return result


if __name__ == "__main__":
    main()
