"""`mergesvc projection make|show|check`: the fleet's projection, the file the compact profile
codes embeddings on (docs/wire.md §5). One file, made once and given to the service
(`serve --projection`) and to every vehicle (`agent --projection`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from mergesvc.cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, exit_on_error, fail
from mergesvc.cli.files import CodecSettingsFile
from mergesvc.cli.options import command_group, resolve_settings
from mergesvc.errors import InputError, MergeError

if TYPE_CHECKING:
    import numpy as np

projection_app = command_group("the fleet's projection (compact profile)")


def _embeddings_of(path: Path) -> np.ndarray:
    """(n, d) embeddings of a map or submap JSON file, a wire message (.bin, not compact) or
    a numpy array file (.npy, (n, d))."""
    import numpy as np

    from mergesvc.core.model import ObjectMap
    from mergesvc.wire import decode_message
    from mergesvc.wire.files import load_objects

    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            E = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise InputError(f"cannot read {path}: {exc}") from exc
        if E.ndim != 2 or E.dtype.kind not in "fiu":
            raise InputError(f"{path}: expected an (n, d) array of numbers, got {E.shape}")
        return E.astype(np.float64)
    if suffix == ".bin":
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InputError(f"cannot read {path}: {exc.strerror or exc}") from exc
        _, model = decode_message(data)
        if not isinstance(model, ObjectMap):
            raise InputError(f"{path}: a {type(model).__name__} message holds no embeddings")
        return model.arrays().embeddings_nd
    return load_objects(path).arrays().embeddings_nd


def _describe(proj: Any, budget_bits: int) -> dict[str, Any]:
    import numpy as np

    bits = proj.bit_allocation(budget_bits)
    kept = proj.variance_kept
    scale2 = proj.scale_k.astype(np.float64) ** 2
    return {
        "id": proj.id, "dim": proj.dim, "k": proj.k,
        "variance_kept": None if kept is None else round(kept, 4),
        "budget_bits": budget_bits,
        "components_with_bits": int(np.count_nonzero(bits)),
        "variance_with_bits": round(float(scale2[bits > 0].sum() / scale2.sum()), 4),
    }


@projection_app.command("make")
def make(
    out: Annotated[Path, typer.Argument(help="the projection file to write (.npz)")],
    from_: Annotated[
        list[Path] | None,
        typer.Option("--from", help="embeddings to fit on: map or submap JSON files, "
                                    "wire messages (.bin) or (n, d) arrays (.npy)"),
    ] = None,
    survey: Annotated[
        str | None,
        typer.Option(help="fit on a simulated survey of this world instead: underwater or "
                          "kitti (the demo's: underwater with the demo's --seed)"),
    ] = None,
    seed: Annotated[int, typer.Option(help="seed of the survey and of the subsample")] = 0,
    samples: Annotated[int, typer.Option(help="views in the simulated survey")] = 4000,
    k: Annotated[int | None, typer.Option(help="components kept [default: all the data "
                                               "supports]")] = None,
    max_samples: Annotated[int, typer.Option(help="fit on a seeded random subset of at most "
                                                  "this many embeddings")] = 20_000,
    settings: CodecSettingsFile = None,
) -> None:
    """Make the fleet's projection: a PCA of embeddings the fleet already shares (a survey,
    maps of earlier missions), not of what it will send. Give the same file to `serve
    --projection` and to every `agent --projection`."""
    import numpy as np

    from mergesvc.sim import Family, survey_embeddings
    from mergesvc.wire import Projection

    if (survey is None) == (not from_):
        fail(InputError("give either --from FILE (one or more) or --survey underwater|kitti"),
             EXIT_BAD_INPUT)
    with exit_on_error(ValueError, OSError):
        codec = resolve_settings(settings).codec
        if survey is not None:
            E = survey_embeddings(seed, Family(survey), samples)
        else:
            parts = [_embeddings_of(p) for p in from_ or []]
            dims = {e.shape[1] for e in parts}
            if len(dims) != 1:
                raise InputError(f"the files hold embeddings of {len(dims)} sizes "
                                 f"({', '.join(map(str, sorted(dims)))}): one fleet, one size")
            E = np.concatenate(parts)
        proj = Projection.fit(E, k, max_samples=max_samples, seed=seed)
        proj.save(out)
    info = _describe(proj, codec.embedding_bits)
    kept = info["variance_kept"]
    typer.echo(f"wrote {out}: projection {proj.id}, {proj.dim}-d -> {proj.k} components from "
               f"{min(len(E), max_samples)} embeddings, {100 * kept:.1f} % of their variance; "
               f"give it to `mergesvc serve --projection {out}` and to every "
               f"`mergesvc agent --projection {out}`")


@projection_app.command("show")
def show(
    path: Annotated[Path, typer.Argument(help="a projection file (.npz)")],
    settings: CodecSettingsFile = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
) -> None:
    """Print a projection's id, dimensions and the variance it keeps; and, at the codec's
    budget (codec.embedding_bits), how many components get bits."""
    from mergesvc.wire import Projection

    with exit_on_error():
        codec = resolve_settings(settings).codec
        info = _describe(Projection.load(path), codec.embedding_bits)
    if as_json:
        typer.echo(json.dumps(info))
        return
    kept = "not recorded" if info["variance_kept"] is None else (
        f"{100 * info['variance_kept']:.1f} % of the fit data's")
    typer.echo(f"projection {info['id']}: {info['dim']}-d embeddings -> {info['k']} components;"
               f" variance kept: {kept}")
    typer.echo(f"at {info['budget_bits']} bits/object: {info['components_with_bits']} "
               f"components get bits ({100 * info['variance_with_bits']:.1f} % of the kept "
               "variance)")


@projection_app.command("check")
def check(
    path: Annotated[Path, typer.Argument(help="a projection file (.npz)")],
    files: Annotated[list[Path], typer.Argument(help="map or submap JSON files or wire "
                                                     "messages (.bin) to check")],
    min_cosine: Annotated[float, typer.Option(help="fail a file whose objects come back, on "
                                                   "average, less alike than this")] = 0.0,
    settings: CodecSettingsFile = None,
) -> None:
    """Whether each file can be coded `compact` with this projection (or, a compact message,
    was coded with it), and how alike its embeddings come back (cosine to the original).
    Exit 1 when one cannot."""
    from mergesvc.wire import Projection, decode_message
    from mergesvc.wire.envelope import peek_compact_code
    from mergesvc.wire.projection import CompactCode, compact_cosine

    with exit_on_error():
        codec = resolve_settings(settings).codec
        proj = Projection.load(path)
    code = CompactCode(proj.id, codec.embedding_bits, max(1, round(codec.coef_step_scale * 16)))
    bad = 0
    for f in files:
        with exit_on_error(ValueError, OSError):
            if f.suffix.lower() == ".bin" and (used := peek_compact_code(f.read_bytes())):
                if used.projection_id != proj.id:
                    typer.echo(f"{f}: NO: coded with projection {used.projection_id}, not "
                               f"{proj.id}")
                    bad += 1
                    continue
                decode_message(f.read_bytes(), proj)
                typer.echo(f"{f}: ok: coded with this projection")
                continue
            E = _embeddings_of(f)
        if E.shape[1] != proj.dim:
            typer.echo(f"{f}: NO: {E.shape[1]}-d embeddings, the projection is {proj.dim}-d")
            bad += 1
            continue
        cos = compact_cosine(E, proj, code)
        ok = float(cos.mean()) >= min_cosine
        bad += not ok
        typer.echo(f"{f}: {'ok' if ok else 'NO'}: {len(E)} objects come back with cosine "
                   f"{cos.mean():.3f} on average (lowest {cos.min():.3f})"
                   + ("" if ok else f", below --min-cosine {min_cosine}"))
    if bad:
        fail(MergeError(f"{bad} of {len(files)} files cannot be coded with projection "
                        f"{proj.id}"), EXIT_FAILED)
