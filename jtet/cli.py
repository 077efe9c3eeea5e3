"""The ``jtet`` command: ``jtet improve``, ``jtet stats``, ``jtet convert``,
``jtet tetrahedralize``, ``jtet demo``.

Exit codes: 0 success (also when ``--time-limit`` or the goals stopped the run: OUT holds
the best mesh so far); 2 bad input or options (one line on stderr says why); 3 ``--check`` found
an invariant violation (one line on stderr; OUT is not written); 130 interrupted (Ctrl-C):
when the optimizer was running, OUT holds the best valid mesh so far (written
atomically), otherwise nothing was written. OUT is never left partially written.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import sys
import time
import warnings
from pathlib import Path

from ._errors import JtetError
from ._options import OPS, Options
from ._quality import MEASURES

DEFAULTS = Options()


def _ops(text: str) -> tuple[str, ...]:
    ops = tuple(o.strip() for o in text.replace("+", ",").split(",") if o.strip())
    bad = [o for o in ops if o not in OPS]
    if bad or not ops:
        raise argparse.ArgumentTypeError(f"unknown operation(s) {bad}; choose from {','.join(OPS)}")
    return ops


def _regions(text: str) -> tuple[int | str, ...] | None:
    """Region labels, or names of Gmsh physical volumes (``improve`` resolves them)."""
    if text.strip().lower() == "none":
        return None
    parts = [r.strip() for r in text.split(",")]
    if not all(parts):
        raise argparse.ArgumentTypeError(
            f"expected comma-separated region labels or names, got {text!r}"
        )
    return tuple(int(r) if r.lstrip("+-").isdigit() else r for r in parts)


def _perturb(text: str) -> int | str:
    """``--perturb``: a count of kept rounds (>= 0) or ``auto``."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a count >= 0 or 'auto', got {text!r}")
    return value


def _add_quality(p: argparse.ArgumentParser, help: str) -> None:
    p.add_argument("--quality", choices=sorted(MEASURES), default=DEFAULTS.quality, help=help)


def _add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--options",
        metavar="FILE",
        help="options from a JSON / YAML file: a mapping of jtet.Options fields, a "
        "--report file (runs again with its options) or a configs/optimizer file; the "
        "flags given here override it",
    )
    p.add_argument(
        "--ops",
        type=_ops,
        default=DEFAULTS.ops,
        help="comma-separated operations (default: edge,face,smooth)",
    )
    _add_quality(p, "quality measure to maximize")
    p.add_argument(
        "--max-ring",
        type=int,
        default=DEFAULTS.max_ring,
        help="largest ring tried by edge removal (3..16)",
    )
    p.add_argument(
        "--max-faces",
        type=int,
        default=DEFAULTS.max_faces,
        help="capacity of a multi-face removal tree",
    )
    p.add_argument(
        "--boundary",
        choices=("fixed", "slide"),
        default=DEFAULTS.boundary,
        help="boundary vertices stay fixed or slide in flat facets / straight segments",
    )
    p.add_argument(
        "--feature-angle",
        type=float,
        default=DEFAULTS.feature_angle,
        help="degrees; subfacets bent more than this are features, smaller bends may be "
        "flipped, changing the surface's shape (default 0: exactly flat only)",
    )
    p.add_argument(
        "--regions",
        type=_regions,
        default=DEFAULTS.regions,
        metavar="R1,R2",
        help="improve only the tets of these regions (labels, or names of Gmsh physical "
        "volumes); the other regions, and the faces they share with these, stay exactly "
        "as they are ('none', the default: all)",
    )
    p.add_argument("--max-passes", type=int, default=DEFAULTS.max_passes)
    p.add_argument(
        "--patience",
        type=int,
        default=DEFAULTS.patience,
        help="stop after this many passes in a row without progress",
    )
    p.add_argument(
        "--perturb",
        type=_perturb,
        default=DEFAULTS.perturb,
        metavar="N",
        help="after the climb converges, up to N kept rounds of kicks around the worst "
        "tets (flips that may lower them a little, new vertices, random moves), each kept "
        "only if the climb that follows ends better (0: off; 'auto', the default: 8 up to "
        "100k tets, more on larger meshes: 14 at 1M)",
    )
    p.add_argument(
        "--insert",
        action=argparse.BooleanOptionalAction,
        default=DEFAULTS.insert,
        help="let the perturbation rounds add vertices (the default); --no-insert keeps the "
        "input's points: the output has exactly its vertices, in their order",
    )
    p.add_argument(
        "--time-limit",
        type=float,
        default=None,
        metavar="S",
        help="stop after S seconds, keeping the best mesh so far",
    )
    p.add_argument(
        "--goal-min-dihedral",
        type=float,
        default=None,
        metavar="DEG",
        help="stop once the smallest dihedral angle is at least DEG (and the largest meets "
        "--goal-max-dihedral, if given)",
    )
    p.add_argument(
        "--goal-max-dihedral",
        type=float,
        default=None,
        metavar="DEG",
        help="stop once the largest dihedral angle is at most DEG (and the smallest meets "
        "--goal-min-dihedral, if given)",
    )
    p.add_argument(
        "--min-progress",
        type=float,
        default=DEFAULTS.min_progress,
        help="relative rise of the worst quality or of the worst tets' thresholded means "
        "that counts as progress",
    )
    p.add_argument(
        "--good-quality",
        type=_optional_float,
        default=DEFAULTS.good_quality,
        metavar="Q",
        help="leave tets of at least this quality alone ('none': work everywhere)",
    )
    p.add_argument(
        "--min-improvement",
        type=float,
        default=DEFAULTS.min_improvement,
        help="an operation must raise its worst tet's quality by more than this",
    )
    p.add_argument(
        "--smooth-threshold",
        type=_optional_float,
        default=DEFAULTS.smooth_threshold,
        metavar="Q",
        help="smooth only vertices of tets below this quality ('none', the default: every "
        "vertex of a tet below --good-quality)",
    )
    p.add_argument(
        "--min-scaled-jacobian",
        type=_optional_float,
        default=DEFAULTS.min_scaled_jacobian,
        metavar="J",
        help="curved tets (a quadratic input read with --linear): no change may bend one "
        "below this scaled Jacobian (Gmsh's minSJ) unless the tets it replaces were "
        f"worse already (default {DEFAULTS.min_scaled_jacobian}; 'none': no guard)",
    )
    p.add_argument("--seed", type=int, default=DEFAULTS.seed)
    p.add_argument("--check", action="store_true", help="verify invariants after every operation")


def _optional_float(text: str) -> float | None:
    return None if text.lower() == "none" else float(text)


def _options_from(args) -> Options:
    names = {f.name for f in dataclasses.fields(Options)}
    kw = {k: v for k, v in vars(args).items() if k in names}
    return Options(**kw)


class _Progress:
    """A one-line progress bar on stderr (plain lines when stderr is not a terminal);
    ``prefix`` tells which file of a batch it is."""

    def __init__(self, max_passes: int, quiet: bool, prefix: str = ""):
        self.max_passes = max(max_passes, 1)
        self.quiet = quiet
        self.prefix = prefix
        self.tty = sys.stderr.isatty()
        self.t0 = time.perf_counter()

    def __call__(self, e: dict) -> None:
        if self.quiet:
            return
        frac = min((e["pass"] + 1) / self.max_passes, 1.0)
        bar = "#" * int(20 * frac) + "." * (20 - int(20 * frac))
        if e["op"] == "perturb":  # one attempt of a perturbation round
            verdict = "kept" if e["successes"] else "gave up" if e["gave_up"] else "undone"
            what = f"perturb {e['kick']:7s} {verdict:7s}"  # 7: the longest kick name (jiggle0)
        else:
            what = f"pass {e['pass'] + 1} {e['op']:6s} {e['successes']:6d}/{e['attempts']:<7d}"
        msg = (
            f"{self.prefix}[{bar}] {what} min/max dihedral {e['min_dihedral']:6.2f}/{e['max_dihedral']:6.2f}  "
            f"{time.perf_counter() - self.t0:6.1f}s"
        )
        if self.tty:
            print("\r" + msg, end="", file=sys.stderr, flush=True)
        else:
            print(msg, file=sys.stderr, flush=True)

    def done(self) -> None:
        if self.tty and not self.quiet:
            print(file=sys.stderr)


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _improve_and_save(mesh, out: Path, args, prefix: str = ""):
    """Improve ``mesh`` with the options of ``args`` and write the result to ``out``;
    returns (the ``ImproveResult``, exit code: 0, 3 (invariant violation: nothing
    written) or 130 (interrupted: the best mesh so far written))."""
    from ._driver import improve
    from ._io import save
    from ._report import quality_cell_data

    opts = _options_from(args)
    progress = _Progress(opts.max_passes, args.quiet, prefix)
    result = improve(mesh, opts, callback=progress)
    progress.done()
    if result.status.startswith("invariant violation"):
        print(f"jtet: error: {result.status}; {out} not written", file=sys.stderr)
        return result, 3
    quadratic = getattr(args, "quadratic", False)
    save(result.mesh, out, cell_data=quality_cell_data(result.mesh), quadratic=quadratic)
    if result.status == "interrupted":
        print(f"jtet: interrupted; wrote the best mesh so far to {out}", file=sys.stderr)
        return result, 130
    return result, 0


def _run_improve(mesh, out: Path, args, source: str) -> int:
    from ._report import plot_run, write_report

    result, code = _improve_and_save(mesh, out, args)
    if code == 3:
        return 3
    if args.report:
        write_report(result, args.report)
    if args.plot:
        plot_run(result, args.plot)
    if not args.quiet:
        print(f"jtet: {source} -> {out}  ({result.status}, {result.seconds:.1f} s)")
        print(result.summary())
        for extra in (args.report, args.plot):
            if extra:
                print(f"wrote {extra}")
    return code


def _same_path(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file: one resolved path, or one existing file
    (a hard link)."""
    return a.resolve() == b.resolve() or _same_file(a, b)


def _input_written(src: Path, out: Path) -> Path | None:
    """The file of the input ``src`` that saving to ``out`` would replace, or None: the
    input itself, or one of its companions (a TetGen .node / .ele / .face, the HDF5 file
    of an XDMF mesh), as ``jtet improve a.node a.ele`` would replace a.node."""
    from ._io import read_files, written_files

    reads = read_files(src)
    return next((w for w in written_files(out) for r in reads if _same_path(w, r)), None)


def _refuse_input_as_output(src: Path, out: Path, overwrite: bool) -> None:
    """Refuse (``JtetError``) to write ``out`` where it would replace a file of the input
    ``src``, unless ``overwrite``."""
    hit = None if overwrite else _input_written(src, out)
    if hit is None:
        return
    if _same_path(src, out):
        raise JtetError(f"{out} is the input file; pass --overwrite to replace it")
    if _same_path(src, hit):
        raise JtetError(
            f"writing {out} also writes {hit}, the input file; pass --overwrite to replace it"
        )
    raise JtetError(
        f"writing {out} also writes {hit}, which the input {src} reads; pass --overwrite "
        "to replace it"
    )


def cmd_improve(args) -> int:
    if args.out_dir is not None:
        return _improve_batch(args)
    if args.out_ext is not None:
        raise JtetError("--out-ext names the outputs of --out-dir")
    if len(args.paths) != 2:
        raise JtetError(
            f"jtet improve takes IN OUT, or several inputs with --out-dir DIR "
            f"({len(args.paths)} path(s) given)"
        )
    from ._io import output_format

    src, out = (Path(p) for p in args.paths)
    output_format(out)  # an unknown extension fails before the input is read
    _refuse_input_as_output(src, out, args.overwrite)
    mesh = _read_input(src, args)
    return _run_improve(mesh, out, args, str(src))


def _batch_plot(plot: str, out: Path) -> Path:
    """The figure of one file of a batch: ``--plot H.png`` with the output's name
    added, H_<output stem>.png."""
    p = Path(plot)
    return p.with_name(f"{p.stem}_{out.stem}{p.suffix}")


def _batch_outputs(args) -> list[tuple[Path, Path]]:
    """(input, output) of every file of ``jtet improve IN... --out-dir DIR``, checked
    before any run: a known output format, no two inputs to one output (nor to one
    figure, with --plot), no input overwritten without --overwrite."""
    from ._io import output_format, read_files, written_files

    if args.plot and not Path(args.plot).parent.is_dir():
        raise JtetError(f"--plot {args.plot}: {Path(args.plot).parent} is no existing directory")
    outdir = Path(args.out_dir)
    if not outdir.is_dir():
        raise JtetError(f"--out-dir {outdir}: not an existing directory")
    ext = args.out_ext
    if ext is not None and not ext.startswith("."):
        ext = "." + ext
    pairs = []
    for path in args.paths:
        src = Path(path)
        out = outdir / (src.stem + (ext or src.suffix))
        output_format(out)
        _refuse_input_as_output(src, out, args.overwrite)
        pairs.append((src, out))
    seen, plots = {}, {}
    # another input's files too: a run writes its output before the next input is read
    # (a.xdmf's a.h5 may be the heavy data of the input b.xdmf)
    reads = {r.resolve(): src for src, _ in pairs for r in read_files(src)}
    for src, out in pairs:
        key = out.resolve()
        if key in seen:
            raise JtetError(f"{seen[key]} and {src} would both be written to {out}")
        seen[key] = src
        for w in written_files(out):
            other = reads.get(w.resolve())
            if other is not None and other != src and not args.overwrite:
                raise JtetError(
                    f"writing {out} (the output of {src}) also writes {w}, which the input "
                    f"{other} reads; pass --overwrite to replace it"
                )
        if args.plot:
            plot = _batch_plot(args.plot, out)
            if plot.resolve() in plots:
                raise JtetError(
                    f"{plots[plot.resolve()]} and {src} would both be plotted to {plot}"
                )
            plots[plot.resolve()] = src
    return pairs


def _improve_batch(args) -> int:
    """``jtet improve IN... --out-dir DIR``: every input improved in this one process
    (jtet's import and kernels are loaded once, not once per file), the output written
    as DIR/<input name> (``--out-ext``: another format). An input that cannot be read
    or written is reported and skipped; Ctrl-C stops the batch after writing the
    current file's best mesh. Exit code: the worst of the files' (130 > 3 > 2 > 0)."""
    from ._report import plot_run, write_text_atomic
    from ._stats import text_table

    pairs = _batch_outputs(args)
    rows, reports, codes = [], [], [0]
    partial = False  # a row shows only the tets a part run could change
    for i, (src, out) in enumerate(pairs):
        try:
            mesh = _read_input(src, args)
            result, code = _improve_and_save(mesh, out, args, f"[{i + 1}/{len(pairs)}] ")
        except JtetError as e:
            print(f"jtet: error: {e}", file=sys.stderr)
            rows.append([str(src), "-", "-", "-", "error", "-"])
            reports.append({"input": str(src), "output": None, "error": str(e)})
            codes.append(2)
            continue
        codes.append(code)
        before, after = result.stats_before, result.stats_after
        mark = ""
        if result.selected_stats is not None:  # regions / protected tets: the part's own
            (before, after), mark, partial = result.selected_stats, " *", True
        written = code != 3
        rows.append(
            [
                str(src) + mark,
                f"{before.n_tets} -> {after.n_tets}",
                f"{before.min_dihedral:.2f} -> {after.min_dihedral:.2f}",
                f"{before.max_dihedral:.2f} -> {after.max_dihedral:.2f}",
                result.status if written else "not written",
                f"{result.seconds:.1f}",
            ]
        )
        reports.append({"input": str(src), "output": str(out) if written else None,
                        **result.as_dict()})  # fmt: skip
        plot = _batch_plot(args.plot, out) if args.plot else None
        if plot is not None:
            plot_run(result, plot)
        if not args.quiet:
            drawn = f"; {plot}" if plot is not None else ""
            print(
                f"jtet: {src} -> {out}{drawn}  ({result.status}, {result.seconds:.1f} s)",
                flush=True,
            )
        if code == 130:
            break
    if args.report:
        import json

        write_text_atomic(args.report, json.dumps(reports, indent=1))
    if not args.quiet:
        head = ["input", "tets", "min dihedral", "max dihedral", "status", "s"]
        print(text_table(head, rows))
        if partial:
            print("* the tets the run could change (its regions, unprotected tets) only")
        if args.report:
            print(f"wrote {args.report}")
    return 130 if 130 in codes else 3 if 3 in codes else max(codes)


def cmd_stats(args) -> int:
    import json

    if args.worst < 0:
        raise JtetError(f"--worst must be >= 0, got {args.worst}")
    # every file is read before anything is printed: a bad one is the only output; one
    # mesh at a time is held, only its (small) results are kept
    files = [
        _mesh_summary(path, args.worst, args.quality, args.by_region, args.groups, args.linear)
        for path in args.mesh
    ]
    stats = [f["stats"] for f in files]
    labels = _column_labels(args.mesh)
    # a column per file, each followed, with --by-region, by one per region of it (one
    # file: "value", or "whole mesh" and "region 2 (fluid)" without the file's name)
    table_stats, table_labels = [], []
    for col, f in zip(labels, files, strict=True):
        table_stats += [f["stats"], *f["regions"].values()]
        regions = [_region_name(r, f["names"]) for r in f["regions"]]
        if len(files) == 1:
            table_labels += ["whole mesh" if regions else "value", *regions]
        else:
            table_labels += [col, *(f"{col}: {name}" for name in regions)]
    if args.plot:
        from ._report import plot_stats

        plot_stats(stats, args.plot, labels, args.quality)
    if args.json:
        rows = [
            {"file": path, "valid": f["validity"].ok, **f["stats"].as_dict()}
            | ({"worst": f["worst"]} if args.worst else {})
            | (
                {"regions": {str(r): st.as_dict() for r, st in f["regions"].items()}}
                if args.by_region
                else {}
            )
            | ({"groups": f["groups"]} if args.groups else {})
            | ({"curved": f["curved"]} if f["curved"] else {})
            for path, f in zip(args.mesh, files, strict=True)
        ]
        if len(files) == 1:  # one mesh: its statistics, as before there were several
            del rows[0]["file"], rows[0]["valid"]
        print(json.dumps(rows[0] if len(files) == 1 else rows))
        return 0
    from ._stats import format_table, format_worst

    for path, f in zip(args.mesh, files, strict=True):
        print(f"{path}: {f['mesh']}")
    print(format_table(*table_stats, labels=table_labels))
    for path, f in zip(args.mesh, files, strict=True):
        report = f["validity"]
        name = "" if len(files) == 1 else f"{path}: "
        if report.ok:  # and its notes: unreferenced or coincident points
            print("\n".join([f"{name}valid", *(f"{name}note: {n}" for n in report.notes())]))
        else:
            print(f"{name}problems:\n{report}")
        if f["curved"]:
            c = f["curved"]
            print(
                f"{name}quadratic: {c['edges']} curved edges ({c['surface_edges']} bend a "
                f"bounding surface: improve flips none of them); {c['folded_tets']} tet(s) "
                "folded (a non-positive Jacobian at a node); smallest scaled Jacobian "
                f"(Gmsh's minSJ) {c['min_scaled_jacobian']:.3f}"
            )
    if args.groups:
        from ._stats import format_groups

        for path, f in zip(args.mesh, files, strict=True):
            print(f"\n{path}: groups")
            print(format_groups(f["groups"]))
    if args.worst:
        for path, f in zip(args.mesh, files, strict=True):
            print(f"\n{path}: the {len(f['worst'])} worst tets by {args.quality}")
            print(format_worst(f["worst"], args.quality))
    if args.plot:
        print(f"wrote {args.plot}")
    return 0


def _mesh_summary(
    path: str,
    n_worst: int,
    measure: str,
    by_region: bool = False,
    groups: bool = False,
    linear: bool = False,
) -> dict:
    """What ``jtet stats`` prints of one file: the mesh's one-line description, its
    statistics (and, ``by_region``, those of each region), validity report, ``n_worst``
    worst tets by ``measure`` and (``groups``) its regions, labels and node sets."""
    from ._io import load
    from ._quality import tet_all_measures
    from ._stats import mesh_groups, mesh_stats, region_stats, worst_tets

    mesh = load(path, linear=linear)
    per_tet = tet_all_measures(mesh.points, mesh.tets)
    try:
        regions = region_stats(mesh, per_tet=per_tet) if by_region else {}
    except JtetError as e:
        raise JtetError(f"{path}: {e}") from None
    curved = None
    if mesh.has_curved_edges:  # a quadratic file read with --linear: its tets as written
        from ._curved_guard import surface_curved_edges
        from ._quadratic import folded_tets, quadratic_mesh

        n_folded, smallest = folded_tets(quadratic_mesh(mesh))
        curved = {
            "edges": len(mesh.curved_edges.edges),
            "surface_edges": len(surface_curved_edges(mesh)),
            "folded_tets": n_folded,
            "min_scaled_jacobian": smallest,
        }
    return {
        "mesh": repr(mesh),
        "curved": curved,
        "stats": mesh_stats(mesh, per_tet=per_tet),
        "regions": regions,
        "names": dict(mesh.label_names),
        "validity": mesh.is_valid(),
        "worst": worst_tets(mesh, n_worst, measure, per_tet=per_tet) if n_worst else None,
        "groups": mesh_groups(mesh) if groups else None,
    }


def _region_name(label: int, names: dict) -> str:
    """ "region 2", or "region 2 (fluid)" when the mesh names it (Gmsh physical names)."""
    name = names.get((3, label))
    return f"region {label}" + (f" ({name})" if name else "")


def _column_labels(paths: list[str]) -> list[str]:
    """Short names of the files for table columns and legends: the file names, or the
    paths as given when two files share a name (``a/out.vtu``, ``b/out.vtu``)."""
    names = [Path(path).name for path in paths]
    return names if len(set(names)) == len(names) else list(paths)


def cmd_convert(args) -> int:
    """``jtet convert IN OUT``: the mesh of IN in the format of OUT's extension, with what
    jtet reads and writes of every format (regions, labelled protected faces, edges and
    vertices: Gmsh physical groups, Medit references, TetGen markers, VTK arrays)."""
    from ._io import output_format, save
    from ._report import quality_cell_data

    src, out = Path(args.input), Path(args.output)
    output_format(out)  # an unknown extension fails before the input is read
    _refuse_input_as_output(src, out, args.overwrite)
    mesh = _read_input(src, args)
    cell_data = quality_cell_data(mesh) if args.quality_arrays else None
    save(mesh, out, cell_data=cell_data, quadratic=args.quadratic)
    if not args.quiet:
        print(f"jtet: {src} -> {out}  ({mesh})")
    return 0


@contextlib.contextmanager
def _ticking(label: str, quiet: bool):
    """Show ``label`` and the seconds spent on stderr while the block runs (on a
    terminal; elsewhere one line at the start): for work that reports no progress of
    its own, so that a long run does not look hung."""
    if quiet or not sys.stderr.isatty():
        if not quiet:
            print(f"{label} ...", file=sys.stderr, flush=True)
        yield
        return
    import threading

    t0, stop = time.perf_counter(), threading.Event()

    def show(end: str = "") -> None:
        print(f"\r{label} {time.perf_counter() - t0:6.1f}s", end=end, file=sys.stderr)

    def tick() -> None:
        while not stop.wait(0.5):
            show()

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        show("\n")


def cmd_tetrahedralize(args) -> int:
    """``jtet tetrahedralize SURFACE OUT``: fTetWild's tet mesh of the volume a surface
    file bounds, written with the per-tet quality arrays, ready for ``jtet improve``."""
    from ._io import output_format, save
    from ._report import quality_cell_data
    from ._tetrahedralize import open_edges, read_surface, tetrahedralize

    src, out = Path(args.surface), Path(args.output)
    output_format(out)  # an unknown extension fails before the work
    _refuse_input_as_output(src, out, args.overwrite)
    if args.options and not args.improve:
        raise JtetError("--options sets the optimizer's options: it needs --improve")
    if args.improve:
        _options_from(args)  # bad options fail before fTetWild's work
    t0 = time.perf_counter()
    points, triangles = read_surface(src)
    if not args.quiet:
        n_open = open_edges(triangles)
        shape = "closed" if not n_open else f"not closed: {n_open} open or non-manifold edges"
        size = (
            f"edge length {args.edge_length:g}"
            if args.edge_length is not None
            else f"edge length {args.edge_length_fac:g} x the bounding box diagonal"
        )
        print(
            f"jtet: {src}: {len(points)} points, {len(triangles)} triangles ({shape}); "
            f"fTetWild, {size}, envelope {args.epsilon:g}",
            file=sys.stderr,
        )
    with _ticking("fTetWild", args.quiet):
        mesh = tetrahedralize(
            (points, triangles),
            edge_length=args.edge_length,
            edge_length_fac=args.edge_length_fac,
            epsilon=args.epsilon,
            optimize=not args.no_optimize,
            threads=args.threads,
        )
    if args.improve:
        if not args.quiet:
            print(
                f"jtet: fTetWild: {mesh.n_tets} tets, {mesh.n_points} points in "
                f"{time.perf_counter() - t0:.1f} s; improving them",
                file=sys.stderr,
            )
        return _run_improve(mesh, out, args, f"{src} (fTetWild)")
    cells = quality_cell_data(mesh)
    save(mesh, out, cell_data=cells)
    if not args.quiet:  # the dihedral range from the arrays written, not measured again
        lo, hi = cells["min_dihedral"].min(), cells["max_dihedral"].max()
        print(
            f"jtet: {src} -> {out}  ({mesh.n_tets} tets, {mesh.n_points} points, min / max "
            f"dihedral {lo:.2f} / {hi:.2f} deg, {time.perf_counter() - t0:.1f} s)"
        )
        print(f"improve it with: jtet improve {out} {out.with_stem(out.stem + '_improved')}")
    return 0


def cmd_demo(args) -> int:
    from ._io import demo_mesh

    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    args.report = str(outdir / "demo_report.json")
    args.plot = str(outdir / "demo_histograms.png")
    mesh = demo_mesh()
    return _run_improve(mesh, outdir / "demo_improved.vtu", args, "embedded demo mesh")


def _version_line() -> str:
    """jtet's version and those of what a bug report needs, read from the installed
    packages' metadata (importing jax to ask it would take a second)."""
    import platform
    from importlib import metadata

    from . import __version__

    def version(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "missing"

    names = ("jax", "jaxlib", "numpy", "meshio", "pyvista", "pytetwild", "h5py")
    deps = ", ".join(f"{n} {version(n)}" for n in names)
    return f"jtet {__version__} (Python {platform.python_version()}, {deps})"


class _VersionAction(argparse.Action):
    """``--version``: one unwrapped line, read only when asked for."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(_version_line())
        parser.exit()


def _relabel_pairs(text: str) -> dict[int, int]:
    """``--relabel OLD:NEW[,OLD:NEW...]`` as {old: new}."""
    pairs = {}
    for part in text.split(","):
        old, sep, new = part.partition(":")
        try:
            if not sep:
                raise ValueError
            pairs[int(old)] = int(new)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{part!r} is not OLD:NEW (integer region labels, e.g. 0:1)"
            ) from None
    return pairs


def _add_relabel(p) -> None:
    p.add_argument(
        "--relabel",
        type=_relabel_pairs,
        metavar="OLD:NEW,...",
        help="rename region labels after reading (0:1 puts the tets of a mesh without "
        "labels into region 1: a physical volume of its own in a .msh output)",
    )


def _add_drop(p) -> None:
    p.add_argument(
        "--drop",
        type=lambda text: [n for n in text.split(",") if n],
        metavar="NAME,...",
        help="leave these point or cell data arrays of the input out (an integer cell "
        "array that labels no pieces, whose interfaces improve would keep in place)",
    )


def _add_quadratic(p) -> None:
    p.add_argument(
        "--quadratic",
        action="store_true",
        help="write 10-node tets (6-node protected faces, 3-node protected edges; every "
        "format): a node on each edge, on the input's curved boundary where --linear read "
        "one, else at the edge's midpoint",
    )


def _add_linear(p) -> None:
    p.add_argument(
        "--linear",
        action="store_true",
        help="read quadratic cells (10-node tets, 6-node triangles, 3-node lines) as their "
        "corners and leave out their mid-edge nodes; the output is linear (but with "
        "--quadratic)",
    )


def _read_input(src: Path, args):
    """The mesh of ``src``, its regions renamed by ``--relabel``, without the data
    arrays ``--drop`` names."""
    from ._io import load

    mesh = load(src, linear=getattr(args, "linear", False))
    if getattr(args, "relabel", None):
        try:
            mesh = mesh.relabel(args.relabel)
        except JtetError as e:
            raise JtetError(f"{src}: --relabel: {e}") from None
    drop = set(getattr(args, "drop", None) or ())
    if drop:
        have = [*mesh.point_data, *mesh.cell_data]
        unknown = sorted(drop - set(have))
        if unknown:
            raise JtetError(
                f"{src}: --drop: no point or cell data array {unknown[0]!r} "
                f"(the file has: {', '.join(have) or 'none'})"
            )
        mesh = mesh.replace(
            point_data={k: a for k, a in mesh.point_data.items() if k not in drop},
            cell_data={k: a for k, a in mesh.cell_data.items() if k not in drop},
        )
    return mesh


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="jtet",
        description="Improve the quality of tetrahedral meshes (optimal edge removal, multi-face removal, smoothing).",
    )
    p.add_argument(
        "--version", action=_VersionAction, help="print the versions of jtet and its dependencies"
    )
    sub = p.add_subparsers(dest="command", required=True)
    pi = sub.add_parser("improve", help="improve a mesh file and write the result")
    pi.add_argument(
        "paths",
        nargs="+",
        metavar="IN [OUT]",
        help="input mesh (.vtu .vtk .msh .mesh .meshb .node/.ele .xdmf .inp .vol .exo .med) and output mesh (format "
        "from the extension; carries per-tet quality arrays); with --out-dir, only inputs",
    )
    pi.add_argument(
        "--out-dir",
        metavar="DIR",
        help="improve every input in one process and write each to DIR under its own name "
        "(a table of all of them at the end; --report: one JSON list)",
    )
    pi.add_argument(
        "--out-ext",
        metavar="EXT",
        help="with --out-dir: write the outputs in this format (.vtu, .msh, ...; default: "
        "each input's own)",
    )
    _add_options(pi)
    pi.add_argument(
        "--report", metavar="R.json", help="write a JSON report (options, stats, history)"
    )
    pi.add_argument(
        "--plot",
        metavar="H.png",
        help="write a figure: before/after histograms and the angles after each "
        "operation against time (with --out-dir: one figure per file, H_<output name>.png)",
    )
    _add_relabel(pi)
    _add_drop(pi)
    _add_linear(pi)
    _add_quadratic(pi)
    pi.add_argument("--overwrite", action="store_true", help="allow OUTPUT to be the input file")
    pi.add_argument("-q", "--quiet", action="store_true")
    pi.set_defaults(func=cmd_improve)
    ps = sub.add_parser(
        "stats",
        help="print quality statistics and validity of a mesh, or of several side by side",
    )
    ps.add_argument(
        "mesh", nargs="+", help="mesh file(s); several are compared in one table and plot"
    )
    ps.add_argument(
        "--json",
        action="store_true",
        help="machine-readable output (several meshes: a list, with file and valid)",
    )
    ps.add_argument(
        "--plot", metavar="H.png", help="write histograms of dihedral angles and quality"
    )
    _add_quality(ps, "quality measure of the --plot histogram and of --worst")
    ps.add_argument(
        "--worst",
        type=int,
        default=0,
        metavar="N",
        help="list the N worst tets: index (ParaView cell id of a .vtu), quality, dihedral "
        "angles, region, vertices fixed on the boundary, centroid",
    )
    ps.add_argument(
        "--by-region",
        action="store_true",
        help="a column for each region of each mesh too (at most 16 regions; --json: a "
        "'regions' object)",
    )
    ps.add_argument(
        "--groups",
        action="store_true",
        help="list what the file's groups became: regions, labels of protected surfaces, "
        "curves and points, node sets, with names and sizes (--json: a 'groups' list)",
    )
    _add_linear(ps)
    ps.set_defaults(func=cmd_stats)
    pc = sub.add_parser(
        "convert",
        help="write a mesh in another format, with its regions and labelled surfaces, "
        "curves and points",
    )
    pc.add_argument(
        "input",
        help="input mesh (.vtu .vtk .msh .mesh .meshb .node/.ele .xdmf .inp .vol .exo .med)",
    )
    pc.add_argument("output", help="output mesh (format from the extension)")
    pc.add_argument(
        "--quality-arrays",
        action="store_true",
        help="add the per-tet quality and dihedral arrays (as jtet improve does)",
    )
    _add_relabel(pc)
    _add_drop(pc)
    _add_linear(pc)
    _add_quadratic(pc)
    pc.add_argument("--overwrite", action="store_true", help="allow OUTPUT to be the input file")
    pc.add_argument("-q", "--quiet", action="store_true")
    pc.set_defaults(func=cmd_convert)
    from ._tetrahedralize import EDGE_LENGTH_FAC, EPSILON

    pt = sub.add_parser(
        "tetrahedralize",
        help="mesh the volume a surface file bounds with fTetWild (a mesh to improve)",
    )
    pt.add_argument("surface", help="surface file (.stl .obj .ply .off .vtp .vtk)")
    pt.add_argument("output", help="output mesh (format from the extension)")
    size = pt.add_mutually_exclusive_group()
    size.add_argument(
        "--edge-length", type=float, metavar="L", help="target edge length, in the surface's units"
    )
    size.add_argument(
        "--edge-length-fac",
        type=float,
        default=EDGE_LENGTH_FAC,
        metavar="F",
        help="target edge length as a fraction of the bounding box diagonal "
        f"(default {EDGE_LENGTH_FAC:g})",
    )
    pt.add_argument(
        "--epsilon",
        type=float,
        default=EPSILON,
        metavar="E",
        help="how far the boundary may lie from the surface, as a fraction of the bounding "
        f"box diagonal (default {EPSILON:g})",
    )
    pt.add_argument(
        "--no-optimize",
        action="store_true",
        help="fTetWild's raw output, without its own optimization (faster, poor tets)",
    )
    pt.add_argument(
        "--threads", type=int, default=0, metavar="N", help="fTetWild's threads (0: all cores)"
    )
    pt.add_argument(
        "--improve",
        action="store_true",
        help="improve fTetWild's mesh with jtet (its default options, or --options) and write "
        "the improved mesh: one command from a surface to a good tet mesh",
    )
    pt.add_argument(
        "--options",
        metavar="FILE",
        help="with --improve: the optimizer's options from a JSON / YAML file (as jtet improve "
        "--options)",
    )
    pt.add_argument("--overwrite", action="store_true", help="allow OUTPUT to be the input file")
    pt.add_argument("-q", "--quiet", action="store_true")
    pt.set_defaults(func=cmd_tetrahedralize, report=None, plot=None)
    pd = sub.add_parser("demo", help="improve the embedded demo mesh and write its outputs")
    pd.add_argument(
        "--out", default="jtet-demo-out", help="output directory (default: ./jtet-demo-out)"
    )
    _add_options(pd)
    pd.add_argument("-q", "--quiet", action="store_true")
    pd.set_defaults(func=cmd_demo)
    p.subcommands = {
        "improve": pi,
        "stats": ps,
        "convert": pc,
        "tetrahedralize": pt,
        "demo": pd,
    }
    return p


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` for the command line: "jtet: warning: <message>"."""
    text = " ".join(str(message).split())
    if category is not UserWarning:  # e.g. a library's RuntimeWarning: say which kind
        text = f"{text} ({category.__name__})"
    print(f"jtet: warning: {text}", file=sys.stderr if file is None else file)


def _with_options_file(parser: argparse.ArgumentParser, args, argv):
    """``args`` parsed again with the options of ``args.options`` (a file) as the
    defaults of the subcommand, so that the flags on the command line override them."""
    from ._options import load_options

    values = load_options(args.options).as_dict()
    values.pop("progress")  # the command line shows its own progress (-q: none)
    parser.subcommands[args.command].set_defaults(**values)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from ._interrupt import catch_ctrl_c, pressed

    try:
        # a Ctrl-C is remembered even if JAX's gc callback swallows it, from jtet's import
        # on (reading the input included): the optimizer then stops and 130 is returned
        with catch_ctrl_c(earlier=True), warnings.catch_warnings():
            # jtet's warnings about the user's data as one line each, like its errors,
            # without Python's file and source line (once per distinct message)
            warnings.simplefilter("default")
            warnings.showwarning = _show_warning
            if pressed():  # while jtet was imported: do nothing at all
                raise KeyboardInterrupt
            if getattr(args, "options", None):
                args = _with_options_file(parser, args, argv)
            return args.func(args)
    except JtetError as e:
        print(f"jtet: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # outputs are written atomically: each one is complete or absent
        print("jtet: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # stdout closed early (``jtet stats m.vtu | head``): not an error of jtet's
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def run() -> None:
    """The ``jtet`` console command: ``main()``, then a quick exit with its code.

    After a run, the interpreter's own exit spent ~0.75 s tearing down XLA's CPU client,
    its thread pools and the loaded kernels (a 10k-tet ``jtet improve``: 3.9 s with it,
    3.2 s without, mean of 4 alternating runs), more than the optimizer took. By then
    every output is complete (written through atomic renames); once the background kernel
    builds have finished (their cache files written) and the streams are flushed, the
    teardown has nothing left to save, so the process ends with ``os._exit``. In-process
    callers (the tests, notebooks) call ``main()`` and keep the normal exit, as does
    ``python -m jtet.cli`` (so that profilers and coverage tools wrapping it can write
    their results at exit).
    """
    code = main()
    from ._aot import join_background

    try:
        join_background()
        if "logging" in sys.modules:
            sys.modules["logging"].shutdown()
    except KeyboardInterrupt:  # a Ctrl-C while the last kernel loads finish
        code = 130
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (BrokenPipeError, ValueError):  # closed early by the reader, or closed
            pass
    os._exit(code)


if __name__ == "__main__":
    sys.exit(main())
