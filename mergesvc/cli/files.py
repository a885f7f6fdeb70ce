"""Commands that read and write files: `match`, `convert`, `example`, `schemas`, `config --dump`,
`codec encode|decode`, `scenario underwater|drive`, `uncertainty train|eval`."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from mergesvc.cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, exit_on_error, fail
from mergesvc.cli.options import (
    DeprecatedConfig,
    SettingsCommand,
    TrajectoryFile,
    bare_match_for,
    check_trajectory,
    command_group,
    deprecated_config,
    given,
    resolve_settings,
    settings_file,
)
from mergesvc.core.names import MatchMode, NodeAffinity, SolverName
from mergesvc.errors import InputError, MergeError, one_line
from mergesvc.wire.names import Profile

if TYPE_CHECKING:
    from mergesvc.core.model import MatchResult

codec_app = command_group("the wire codec")
scenario_app = command_group("seeded worlds with ground truth")
uncertainty_app = command_group("the learned image-uncertainty head")

# --settings of each command here: what it reads
MatchSettings = settings_file("`match`", bare="MatchConfig")
DumpSettings = settings_file(
    "the whole tree", bare="MatchConfig (placed as --for says) or UncertaintyConfig"
)
CodecSettingsFile = settings_file("`codec`")
UncertaintySettings = settings_file("`uncertainty`", bare="UncertaintyConfig")


def _warn_zero_embeddings(path: Path, objs: Any) -> None:
    """One warning line on stderr for a file's objects whose embedding is all zeros: their
    cosine with anything is 0, so nothing matches them by appearance (a detector's fault)."""
    import numpy as np

    if hasattr(objs, "norms_n"):  # arrays (a binary file): the norms the match computed
        zero = [objs.ids[k] for k in np.flatnonzero(objs.norms_n == 0)]
    else:
        zero = [o.id for o in objs.objects if not any(o.embedding)]
    ids, n = zero[:4], len(zero)
    if n:
        more = ", ..." if n > len(ids) else ""
        typer.echo(f"warning: {path}: {n} object{'' if n == 1 else 's'} with an all-zero "
                   f"embedding ({', '.join(ids)}{more}): nothing matches "
                   f"{'it' if n == 1 else 'them'} by appearance", err=True)


# a world family by name (sim.Family), its choices shown as the enums' options show theirs
FamilyName = Annotated[str, typer.Option(metavar="<underwater|kitti>", help="underwater or kitti")]


# what a rejection's reason asks of the user (text output; the JSON carries the reason)
_REJECTION_HINTS = {
    "tilted": "the fit would turn the vertical over: declare `up` in both files (README: Which "
              "way is up)",
    "ambiguous": "look-alikes: another choice explains the submap almost as well; a larger "
                 "submap, or `up` declared in both files, tells them apart",
    "degenerate_geometry": "the matched objects lie on a line or one above another: objects "
                           "off that line are needed",
    "too_few_matches": "a fit needs 3 matches (2 with `up` declared in both files)",
    "residual_too_large": "the matches fit no rigid transform within the gate "
                          "(`verify.inlier_sigmas`)",
    "search_incomplete": "the exact search ran out of budget (`verify.max_nodes`, "
                         "`verify.time_limit_s`)",
    "no_candidates": "no map object looks like the submap's: are both files from the same "
                     "embedding model?",
}
# a fit that was found, refused by chance's count (core/chance.py)
_CHANCE_HINT = ("a submap of a place the map does not hold would give an answer this good "
                "{} times: is the vehicle on this map? (`verify.max_chance_log10`, "
                "`max_chance_log10_large`)")


def match(
    ctx: typer.Context,
    map_path: Annotated[Path, typer.Option(
        "--map", help="map file: JSON, or binary (.npz, see `mergesvc convert`)")],
    submap_path: Annotated[Path, typer.Option("--submap", help="submap file: JSON or .npz")],
    mode: Annotated[MatchMode, typer.Option(help="verified (ours) or paper (baseline)")] = (
        MatchMode.VERIFIED
    ),
    solver: Annotated[SolverName, typer.Option(help="graph-matching solver")] = SolverName.RRWM,
    affinity: Annotated[NodeAffinity, typer.Option(help="node affinity")] = NodeAffinity.UCOS,
    settings: MatchSettings = None,
    config: DeprecatedConfig = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
) -> None:
    """Match a submap against a map; print the correspondences and the transform.

    Settings: the `match` section (mergesvc config --dump --section match)."""
    from mergesvc.core.model import ObjectMap, Submap
    from mergesvc.core.pipeline import match as run_match
    from mergesvc.core.solvers.bnb_state import TooLargeError
    from mergesvc.core.threads import list_blas
    from mergesvc.wire.mapfile import is_binary_map, load_arrays

    def load(path: Path, model: type[ObjectMap]) -> Any:
        if is_binary_map(path):
            return load_arrays(path)[0]  # a large one memory-mapped; no per-object models
        from mergesvc.wire.files import load_model

        return load_model(model, path)

    settings = deprecated_config(settings, config, "match")
    flags = given(ctx, mode=mode)
    if given(ctx, solver=solver):
        flags["solver"] = {"name": solver.value}
    if given(ctx, affinity=affinity):
        flags["affinity"] = {"kind": affinity.value}
    with exit_on_error():
        if settings is None and not any(k.startswith("MERGESVC_") for k in os.environ):
            # no file, no environment: the tree's `match` section is the defaults, built
            # without loading the whole settings tree (it imports the service: ~1 s)
            from mergesvc.core.config import match_config

            cfg = match_config(**flags)
        else:
            cfg = resolve_settings(settings, {"match": flags}).match
        map_ = load(map_path, ObjectMap)
        sub = load(submap_path, Submap)
        list_blas()  # set-up, like the imports: not part of the match's timings
        try:
            outcome = run_match(map_, sub, cfg)
        except TooLargeError as exc:
            if cfg.mode is not MatchMode.PAPER:
                raise
            # paper mode's solver runs on every submap x map pair: a flag choice, not a fault
            raise InputError(f"{one_line(exc)}: paper mode solves over every pair; use "
                             "--mode verified, or another --solver") from exc
    for path, objs in ((map_path, map_), (submap_path, sub)):
        _warn_zero_embeddings(path, objs)
    result = outcome.result
    if as_json:
        typer.echo(json.dumps(match_json(result)))
        return
    state = "accepted" if result.accepted else "rejected"
    n = len(result.matches)
    typer.echo(f"{state} ({result.reason.value}): {n} match{'' if n == 1 else 'es'}")
    chance = outcome.extra.get("chance_log10", math.nan)
    if result.reason.value == "too_few_matches" and math.isfinite(chance):
        digits = int(chance < 1)
        times = f"10^{chance:.0f}" if chance >= 6 else f"about {10.0 ** chance:,.{digits}f}"
        typer.echo(f"  hint: {_CHANCE_HINT.format(times)}")
    elif result.reason.value in _REJECTION_HINTS:
        typer.echo(f"  hint: {_REJECTION_HINTS[result.reason.value]}")
    for m in result.matches:
        typer.echo(f"  {m.submap_object:>12} -> {m.map_object:<12} score {m.score:.3f}")
    if result.accepted and result.transform is not None:
        t, q = result.transform.translation, result.transform.quaternion_wxyz
        typer.echo(f"  T_map_submap: t = [{t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}] m, "
                   f"q_wxyz = [{q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f}]")
    typer.echo("  timings (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in result.timings_ms.items()))


def convert(
    in_path: Annotated[Path, typer.Argument(help="map or submap: .json or .npz")],
    out_path: Annotated[Path, typer.Argument(help="file to write: .npz or .json")],
) -> None:
    """Convert a map or submap between JSON and the binary map format (.npz: uncompressed
    numpy arrays, float32 embeddings, memory-mapped by `match`), either way, by suffix."""
    from mergesvc.wire.mapfile import file_to_model, is_binary_map, model_to_file

    with exit_on_error():
        if is_binary_map(in_path) == is_binary_map(out_path):
            raise InputError("convert goes from .json to .npz or from .npz to .json")
        if is_binary_map(out_path):
            from mergesvc.core.model import ObjectMap
            from mergesvc.wire.files import _read_json_model

            model = _read_json_model(in_path)
            if not isinstance(model, ObjectMap):
                raise InputError(f"{in_path} is not a map or submap")
            model_to_file(model, out_path)
        else:
            model = file_to_model(in_path)
            try:
                out_path.write_text(model.model_dump_json(exclude_none=True))
            except OSError as exc:
                raise InputError(f"cannot write {out_path}: {exc.strerror or exc}") from exc
    typer.echo(f"wrote {out_path}: {len(model.objects)} objects")


def match_json(result: MatchResult) -> dict[str, Any]:
    """The one JSON object `match --json` prints (README): the result's keys without
    schema_version; `transform` and `covariance` are null when the match is rejected (a
    rejected fit, e.g. one that would turn the vertical over, is no transform to use)."""
    out = result.cli_dict()
    if not result.accepted:
        out["transform"] = out["covariance"] = None
    return out


def example(
    out_dir: Annotated[Path, typer.Argument(help="folder for map.json, submap.json, truth.json")],
    family: FamilyName = "kitti",
    seed: Annotated[int, typer.Option(min=0, help="scenario seed")] = 0,
) -> None:
    """Write a seeded example map, submap and their ground truth."""
    from mergesvc.sim import Family, make_scenario

    if family not in {f.value for f in Family}:
        fail(InputError(f"--family must be one of {', '.join(f.value for f in Family)}, not "
                        f"{family!r}"), EXIT_BAD_INPUT)
    with exit_on_error(ValueError):
        sc = make_scenario(Family(family), seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "map.json").write_text(sc.map.model_dump_json())
    (out_dir / "submap.json").write_text(sc.submap.model_dump_json())
    (out_dir / "truth.json").write_text(json.dumps(sc.truth_dict(), indent=1))
    typer.echo(
        f"wrote {out_dir}/map.json ({len(sc.map.objects)} objects), submap.json "
        f"({len(sc.submap.objects)} objects), truth.json"
    )


def _folder_to_check(folder: Path, what: str, ours: str) -> None:
    """Exit 2 (one line) when a --check's folder is not there: nothing to compare with."""
    if not folder.is_dir():
        fail(InputError(f"no {what} at {folder}: give the folder to check (the repository's "
                        f"{ours})"), EXIT_BAD_INPUT)


def schemas(
    out_dir: Annotated[Path, typer.Argument(help="folder for the JSON Schema files")] = Path(
        "schemas"
    ),
    check: Annotated[bool, typer.Option(help="fail if the files differ from the models")] = False,
) -> None:
    """Write (or --check) the JSON Schema files generated from the models: the files and
    messages (core), and what the service sends as JSON (fleet/replies.py)."""
    from mergesvc.core.model import json_schemas
    from mergesvc.fleet.replies import reply_schemas

    if check:
        _folder_to_check(out_dir, "schema folder", "schemas/")
    stale = []
    for name, schema in (json_schemas() | reply_schemas()).items():
        text = json.dumps(schema, indent=2, sort_keys=True) + "\n"
        path = out_dir / name
        if check:
            if not path.exists() or path.read_text() != text:
                stale.append(name)
        else:
            out_dir.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    if stale:
        fail(MergeError(f"schemas out of date: {', '.join(stale)}"), EXIT_FAILED)
    typer.echo(f"schemas {'up to date' if check else 'written'} in {out_dir}")


def config(
    dump: Annotated[
        bool, typer.Option("--dump", help="print the resolved settings tree as JSON")
    ] = False,
    settings: DumpSettings = None,
    section: Annotated[
        str | None,
        typer.Option(help="print only this section or field, e.g. service or service.match"),
    ] = None,
    for_: Annotated[
        SettingsCommand | None,
        typer.Option(
            "--for",
            help="show the tree as this command resolves it: a bare MatchConfig file is "
            "service.match for serve, match for any other command (default: both)",
        ),
    ] = None,
) -> None:
    """Print the resolved settings tree (--dump): what a run with these settings uses.

    Defaults <- --settings FILE (else $MERGESVC_SETTINGS) <- MERGESVC_* variables.

    A command's own flags override them for that command. Sections: see mergesvc/settings.py.

    A bare MatchConfig file is service.match for serve, match for any other command.

    --for COMMAND shows the tree as that command resolves it (default: the file in both)."""
    if not dump:
        fail(InputError("nothing to do: mergesvc config --dump [--settings FILE] "
                        "[--section NAME] [--for COMMAND]"), EXIT_BAD_INPUT)
    with exit_on_error():
        tree = resolve_settings(settings, bare_match=bare_match_for(for_))
    data = tree.model_dump(mode="json")
    for part in section.split(".") if section else []:
        if not isinstance(data, dict) or part not in data:
            raise typer.BadParameter(f"no settings under {section}", param_hint="--section")
        data = data[part]
    typer.echo(json.dumps(data, indent=2))


@codec_app.command("encode")
def codec_encode(
    in_path: Annotated[Path, typer.Argument(help="map or submap JSON (the match format)")],
    out_path: Annotated[Path, typer.Argument(help="binary message to write")],
    profile: Annotated[Profile, typer.Option(help="full, f16, int8 or compact")] = (
        Profile.COMPACT
    ),
    projection: Annotated[
        Path | None, typer.Option(help="the fleet's projection (.npz): compact maps and "
                                       "submaps need it (mergesvc projection make)")
    ] = None,
    settings: CodecSettingsFile = None,
) -> None:
    """Encode a map or submap file as one wire message; print bytes per object.

    Settings: the `codec` section."""
    from mergesvc.wire import encode_file

    with exit_on_error():
        codec = resolve_settings(settings).codec
    with exit_on_error(ValueError):
        stats = encode_file(in_path, out_path, profile, projection=projection, settings=codec)
    typer.echo(f"wrote {out_path}: {stats.n_bytes} bytes, {stats.n_objects} objects, "
               f"{stats.bytes_per_object:.1f} bytes/object ({profile.value})"
               + (f", projection {stats.projection_id}" if stats.projection_id else ""))


@codec_app.command("decode")
def codec_decode(
    in_path: Annotated[Path, typer.Argument(help="binary message")],
    out_path: Annotated[Path, typer.Argument(help="JSON file to write (the match format)")],
    projection: Annotated[Path | None, typer.Option(help="fleet projection (.npz)")] = None,
) -> None:
    """Decode a wire message back to the JSON file format `mergesvc match` reads."""
    from mergesvc.wire import decode_file

    with exit_on_error():
        env, model = decode_file(in_path, out_path, projection=projection)
    n = len(getattr(model, "objects", []) or [])
    typer.echo(f"wrote {out_path}: {env.msg_type.value} from {env.sender}, {env.n_bytes} bytes"
               + (f", {n} objects, {env.n_bytes / n:.1f} bytes/object" if n else ""))


@codec_app.command("golden")
def codec_golden(
    out: Annotated[Path, typer.Option(help="folder of the golden vectors")] = Path("tests/golden"),
    check: Annotated[
        bool, typer.Option(help="fail if the folder differs from what this build writes")
    ] = False,
) -> None:
    """Write (or --check) the wire protocol's golden vectors: small messages of every type and
    profile as NAME.bin with the decoded NAME.json (docs/wire.md)."""
    from mergesvc.wire.golden import check_golden, write_golden

    if check:
        _folder_to_check(out, "golden vectors", "tests/golden")
    with exit_on_error():
        if check:
            stale = check_golden(out)
            if stale:
                fail(MergeError(f"golden vectors out of date in {out}: {', '.join(stale)}; "
                                f"run mergesvc codec golden --out {out}"), EXIT_FAILED)
            typer.echo(f"golden vectors up to date in {out}")
            return
        paths = write_golden(out)
    typer.echo(f"wrote {len(paths)} golden files in {out}")


def _write_scenarios(out_dir: Path, run, cases) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "map.json").write_text(run.map.model_dump_json())
    for name, sc in cases:
        (out_dir / f"{name}.json").write_text(sc.submap.model_dump_json())
        (out_dir / f"{name}.truth.json").write_text(json.dumps(sc.truth_dict(), indent=1))
    typer.echo(
        f"wrote {out_dir}/map.json ({len(run.map.objects)} objects) and {len(cases)} submaps "
        f"with a .truth.json beside each; try: mergesvc match --map {out_dir}/map.json "
        f"--submap {out_dir}/{cases[0][0]}.json" if cases else f"wrote {out_dir}/map.json"
    )


@scenario_app.command("underwater")
def scenario_underwater(
    out_dir: Annotated[Path, typer.Argument(help="folder for map.json and the submaps")],
    run: Annotated[int, typer.Option(help="pool run 1, 2 or 3 (the paper's runs)")] = 1,
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    size: Annotated[list[int] | None, typer.Option(help="submap sizes (repeat)")] = None,
    per_size: Annotated[int, typer.Option(help="submaps per size")] = 5,
) -> None:
    """A pool run through the tracker: the first half's map, submaps from the second half."""
    from mergesvc.sim import underwater_run

    if run not in (1, 2, 3) or per_size < 1 or any(k < 1 for k in size or []):
        fail(InputError("--run must be 1, 2 or 3; sizes and --per-size >= 1"), EXIT_BAD_INPUT)
    with exit_on_error():
        r = underwater_run(run, seed)
        cases = [(f"submap_n{k}_{j}", sc) for k in (size or [2, 3, 4, 5])
                 for j, sc in enumerate(r.windows(k, per_size))]
    _write_scenarios(out_dir, r, cases)


@scenario_app.command("drive")
def scenario_drive(
    out_dir: Annotated[Path, typer.Argument(help="folder for map.json and the submaps")],
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    places: Annotated[int, typer.Option(help="loop-closure places")] = 4,
    size: Annotated[int, typer.Option(help="objects per submap")] = 20,
    trajectory: TrajectoryFile = None,
) -> None:
    """A KITTI-like drive through the tracker: the map, submaps at loop-closure places."""
    from mergesvc.sim import drive_run

    check_trajectory(trajectory)
    with exit_on_error():
        try:
            r = drive_run(seed, trajectory)
        except ValueError as exc:
            raise InputError(f"cannot read trajectory {trajectory}: {exc}") from exc
        cases = [(f"place{j + 1}", sc) for j, sc in enumerate(r.places(places, size))]
    _write_scenarios(out_dir, r, cases)


@uncertainty_app.command("train")
def uncertainty_train(
    out: Annotated[Path, typer.Argument(help="weights file to write (.npz)")],
    samples: Annotated[int, typer.Option(help="training observations")] = 20_000,
    seed: Annotated[int, typer.Option(help="world and optimiser seed")] = 0,
    family: FamilyName = "underwater",
    settings: UncertaintySettings = None,
    config: DeprecatedConfig = None,
) -> None:
    """Train the head with the ranking loss on generated observations; report held-out
    Spearman correlation of predicted and true error.

    Settings: the `uncertainty` section (a bare UncertaintyConfig file works too)."""
    import numpy as np

    from mergesvc.sim import Family, image_s_dataset
    from mergesvc.sim.uncertainty import evaluate, fit

    settings = deprecated_config(settings, config, "uncertainty train")
    with exit_on_error():
        cfg = resolve_settings(settings).uncertainty
    with exit_on_error(ValueError):
        fam = Family(family)
    n_test = max(samples // 5, 100)
    with exit_on_error():
        y, loss, _ = image_s_dataset(samples + n_test, seed, fam)
        head, _ = fit(
            y[:samples], loss[:samples], cfg, np.random.default_rng(seed),
            on_epoch=lambda e, m: typer.echo(
                f"epoch {e}: " + ", ".join(f"{k} {v:.4f}" for k, v in m.items()), err=True),
        )
        head.save(out)
    res = evaluate(head, y[samples:], loss[samples:])
    typer.echo(f"wrote {out}; held-out ({n_test}): Spearman {res['spearman']:.3f}, "
               f"Kendall {res['kendall']:.3f}, pairwise accuracy {res['accuracy']:.3f}")


@uncertainty_app.command("eval")
def uncertainty_eval(
    weights: Annotated[Path, typer.Argument(help="weights file (.npz)")],
    samples: Annotated[int, typer.Option(help="test observations")] = 5000,
    seed: Annotated[int, typer.Option(help="world seed the head was trained for")] = 0,
    family: FamilyName = "underwater",
) -> None:
    """Spearman / Kendall / pairwise accuracy of a trained head on fresh observations."""
    from mergesvc.sim import Family, image_s_dataset
    from mergesvc.sim.uncertainty import UncertaintyHead, evaluate

    with exit_on_error(ValueError):
        head = UncertaintyHead.load(weights)
        # fresh objects of the same world: a new draw, not the training one
        y, loss, _ = image_s_dataset(samples, seed, Family(family))
        res = evaluate(head, y, loss)
    typer.echo(json.dumps(res))
