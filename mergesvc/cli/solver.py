"""`mergesvc solver train`: train the neural graph-matching solver (NGM) on generated worlds."""

from __future__ import annotations

import dataclasses
import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated

import typer

from mergesvc.cli.errors import exit_on_error
from mergesvc.cli.options import (
    command_group,
    resolve_settings,
    settings_file,
    write_settings_beside,
)

solver_app = command_group("the neural graph-matching solver (NGM)")

SolverSettings = settings_file(
    "`match` (how the training problems are formulated)", bare="MatchConfig")


@solver_app.command("train")
def solver_train(
    out: Annotated[Path, typer.Option(help="folder for ngm.npz, ngm_weights.py, train.json")] = (
        Path("results/ngm")),
    quick: Annotated[bool, typer.Option(help="a smoke test: a few problems, 2 epochs")] = False,
    seed: Annotated[int, typer.Option(min=0, help="seed of the worlds and the training")] = 0,
    train_problems: Annotated[int | None, typer.Option(
        "--train", min=1, help="training problems (default 900)")] = None,
    val_problems: Annotated[int | None, typer.Option(
        "--val", min=1, help="validation problems (default 150)")] = None,
    epochs: Annotated[int | None, typer.Option(min=1, help="epochs (default 20)")] = None,
    settings: SolverSettings = None,
) -> None:
    """Train NGM on problems from the project's generators (pool runs, drives, drawn scenarios,
    harbour pools in several axis conventions; never the real data) in both formulations,
    seeded. Needs torch: pip install 'mergesvc[train]'.

    Writes OUT/ngm.npz (the weights), OUT/ngm_weights.py (the same weights as the module
    mergesvc ships: copy it over mergesvc/core/solvers/ngm_weights.py to use them) and
    OUT/train.json (settings, loss and validation accuracy per epoch, timings)."""
    import numpy as np

    from mergesvc.core.solvers.ngm import NGMWeights, weights_module_source
    from mergesvc.sim.ngm import TrainConfig, train

    cfg = TrainConfig.quick(seed) if quick else TrainConfig(seed=seed)
    changes = {k: v for k, v in (("n_train", train_problems), ("n_val", val_problems),
                                 ("epochs", epochs)) if v is not None}
    cfg = dataclasses.replace(cfg, **changes)
    with exit_on_error():
        tree = resolve_settings(settings)
        result = train(cfg, echo=lambda m: typer.echo(m, err=True), base=tree.match)
        NGMWeights(result.arrays)  # the numpy forward pass takes them
    report = result.report | {"date": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    meta = {
        "command": "mergesvc solver train" + (" --quick" if quick else "")
        + "".join(f" --{k.removeprefix('n_')} {v}" for k, v in changes.items())
        + f" --seed {seed}",
        "date": report["date"], "torch": report["torch"], "best_epoch": report["best_epoch"],
        "val_accuracy": report["val_accuracy"]["all"],
        "val_accuracy_node_only": report["val_accuracy_node_only"]["all"],
        "elapsed_s": report["elapsed_s"],
    }
    with exit_on_error(OSError):
        out.mkdir(parents=True, exist_ok=True)
        np.savez(out / "ngm.npz", **result.arrays)
        (out / "ngm_weights.py").write_text(weights_module_source(result.arrays, meta))
        (out / "train.json").write_text(json.dumps(report, indent=1, default=float))
        write_settings_beside(tree, out, folder=True)
    v = report["val_accuracy"]
    typer.echo(f"validation accuracy {v['all']:.3f} (paper formulation {v.get('paper', 0):.3f}, "
               f"verified {v.get('verified', 0):.3f}; node affinity alone "
               f"{report['val_accuracy_node_only']['all']:.3f}); {report['elapsed_s']:.0f} s")
    typer.echo(f"wrote {out}/ngm.npz, ngm_weights.py, train.json")
