"""End-to-end scale of a reconstruction: time and peak memory of ``shadecap reconstruct`` against the observed pixels,
from small scenes to real capture sizes, on the CPU and on CUDA (``scripts/benchmark.py scale``).

Each configuration (views × image size, map size) is a synthetic dataset made by ``shadecap synth`` with
:data:`SCALE_SUPERSAMPLE`² jittered rays per pixel — photos the fit's sampling never makes — then reconstructed by
``shadecap reconstruct --model ggx-lambert`` in a process of its own, so that its peak resident memory
(``report.json``'s ``memory``) is its own. The table gives each stage's seconds from the report, the observed
pixels (the footprint fit's kept pixels), the peak memory and its bytes per observed pixel, and the albedo / f0 /
roughness RMSE on the well-lit texels (the accuracy kept at that size). Below the table: the growth exponents of
time and of memory against observed pixels (least squares over the rows of one device; 1 = linear) and the
marginal memory per observed pixel (the slope of peak memory against pixels, which leaves out the fixed cost of the
interpreter, torch and the mesh).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from .timing import growth_exponent, machine_description

__all__ = ["DEFAULT_SCALE_CONFIGS", "SCALE_INTRO", "SCALE_SUPERSAMPLE", "ScaleError", "run_scale_benchmark",
           "scale_run", "scale_table", "race_dataset", "RACE_MODEL"]

#: jittered rays per pixel side of the benchmark's photos: 4 × 4 (not the fit's pixel-centre or stratum-centre
#: sampling) keeps the photos independent of the fit while ``synth`` stays a small share of the benchmark's time at
#: 512² (32 views of 512² at 8 × 8 would cast 537 M rays before the reconstruction starts)
SCALE_SUPERSAMPLE = 4

#: (views, image size, map size) swept by default: views and pixels grow together up to the issue's 32 × 512²
DEFAULT_SCALE_CONFIGS = ((8, 256, 256), (16, 256, 256), (32, 256, 256), (16, 512, 512), (32, 512, 512))

#: the stages of report.json's ``times`` shown, in order
STAGES = ("load", "gbuffer", "observe", "select", "solve", "metrics", "write")


SCALE_INTRO = f"""Each configuration (views × image size, map size) is a synthetic dataset made by `shadecap synth` with
{SCALE_SUPERSAMPLE} × {SCALE_SUPERSAMPLE} jittered rays per pixel — photos the fit's sampling never makes — then
reconstructed by `shadecap reconstruct --model ggx-lambert` in a process of its own, so that the peak memory of
`report.json` is the reconstruction's alone. Stage times come from the report; "observed pixels" are the footprint
fit's kept pixels; the RMSE is on the well-lit texels. Below each table: growth exponents against observed pixels
(1 = linear) and the marginal memory per observed pixel (the slope of peak memory against pixels, without the fixed
cost of the interpreter, torch and the mesh), and against texels where the same photos were fitted on several map
sizes. Plot: `docs/figures/scale.png` (above: against observed pixels, maps the size of the images; below: against
texels, the same photos on finer maps). Regenerate:
`python scripts/benchmark.py scale --devices cpu --threads 2 --rows-json rows.json` on each machine (with
`--devices cuda` where a GPU is), then `python scripts/benchmark.py scale --configs none --earlier ROWS.json ...
--out docs/benchmarks.md --figure docs/figures/scale.png`; the rows shown are kept in `docs/data/scale-*.json`.
"""


class ScaleError(ValueError):
    """A configuration the benchmark cannot run (bad sizes, a failed synth or reconstruct)."""


def _cli(*args: str, threads: int | None) -> None:
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    done = subprocess.run([sys.executable, "-m", "capture.cli", *args], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise ScaleError(f"shadecap {args[0]} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")


def _synth(views: int, image: int, tex: int, work: Path, threads: int | None, model: str | None = None) -> Path:
    """The configuration's dataset in ``work``, synthesised once (with ``model`` instead of synth's default)."""
    for name, v in (("views", views), ("image", image), ("tex", tex)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ScaleError(f"{name} must be a positive integer, got {v!r}")
    data = Path(work) / (f"v{views}-i{image}-t{tex}" + ("" if model is None else "-race"))
    if not (data / "scene.json").is_file():
        _cli("synth", "--out", str(data), "--views", str(views), "--size", str(image), "--tex", str(tex),
             "--supersample", str(SCALE_SUPERSAMPLE), "--overwrite", *(("--model", model) if model else ()),
             threads=threads)
    return data


#: The model of the race against Mitsuba 3's Adam (:func:`race_dataset`): GGX + Lambert with F = 1, which Mitsuba's
#: blend of ``diffuse`` and ``roughconductor`` (material 'none') reproduces exactly (``scripts/mitsuba_adam.py``);
#: the scale scenes' ``ggx-lambert`` has a Schlick Fresnel that no Mitsuba BSDF has.
RACE_MODEL = "lambert+microfacet(D=ggx,G=smith,F=none)"


def race_dataset(views: int, image: int, tex: int, work: Path, threads: int | None = None) -> Path:
    """The race's twin of a configuration: the same rig, mesh, maps and 4 × 4 jittered photos as its scale scene,
    in :data:`RACE_MODEL`; synthesised once into ``work``."""
    return _synth(views, image, tex, Path(work), threads, RACE_MODEL)


def scale_run(views: int, image: int, tex: int, work: Path, device: str = "cpu", threads: int | None = None) -> dict:
    """Synthesise (once; kept in ``work``) and reconstruct one configuration; the row of the table as a dict."""
    t0 = time.perf_counter()
    data = _synth(views, image, tex, Path(work), threads)
    synth_s = time.perf_counter() - t0
    out = Path(work) / f"recon-{data.name}-{device.replace(':', '')}"
    flags = ["--threads", str(threads)] if threads else []
    t0 = time.perf_counter()
    _cli("reconstruct", str(data), "--out", str(out), "--model", "ggx-lambert", "--device", device, "--force",
         *flags, threads=threads)
    wall = time.perf_counter() - t0
    rep = json.loads((out / "report.json").read_text())
    fp = rep["samples"].get("footprints") or {}
    pixels = int(fp.get("pixels") or rep["samples"]["valid"])
    well = rep["errors"].get("maps_by_texel_set", {}).get("well_lit", {})
    return {"machine": machine_description(device, threads), "views": views, "image": image, "tex": tex,
            "device": rep.get("device", device), "synth_s": synth_s,
            "wall_s": wall, "times": rep["times"], "pixels": pixels, "rays": int(fp.get("rays_cast") or pixels),
            "peak_rss_bytes": rep["memory"].get("peak_rss_bytes", 0),
            "cuda_peak_bytes": rep["memory"].get("cuda_peak_bytes"),
            "rmse": {k: v for k, v in well.items() if k != "texels"}}


def _slope(xs: Sequence[float], ys: Sequence[float]) -> float:
    """Least-squares slope of y against x."""
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    den = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / den if den else float("nan")


def _summary_lines(rows: list[dict]) -> list[str]:
    """Per device: growth against observed pixels over the rows whose maps match their images (map size = image
    size: the pixel sweep), and against texels over rows of one views × image with several map sizes."""
    lines = []
    for dev in dict.fromkeys(r["device"] for r in rows):
        rs = [r for r in rows if r["device"] == dev and r["tex"] == r["image"]]
        if len({r["pixels"] for r in rs}) >= 2:
            px = [r["pixels"] for r in rs]
            lines.append(f"- `{dev}`: time ∝ pixels^{growth_exponent(px, [r['times']['total'] for r in rs]):.2f}, "
                         f"solve ∝ pixels^{growth_exponent(px, [r['times'].get('solve', 0.0) for r in rs]):.2f}, "
                         f"peak memory ∝ pixels^{growth_exponent(px, [r['peak_rss_bytes'] for r in rs]):.2f}; "
                         f"marginal memory {_slope(px, [r['peak_rss_bytes'] for r in rs]):.0f} B per observed pixel "
                         f"(maps the size of the images)")
        for views, image in dict.fromkeys((r["views"], r["image"]) for r in rows if r["device"] == dev):
            ts = sorted((r for r in rows if r["device"] == dev and (r["views"], r["image"]) == (views, image)),
                        key=lambda r: r["tex"])
            if len({r["tex"] for r in ts}) < 2:
                continue
            tex = [r["tex"] ** 2 for r in ts]
            lines.append(f"- `{dev}`, {views} × {image}², maps {ts[0]['tex']}² … {ts[-1]['tex']}²: time ∝ "
                         f"texels^{growth_exponent(tex, [r['times']['total'] for r in ts]):.2f}, peak memory ∝ "
                         f"texels^{growth_exponent(tex, [r['peak_rss_bytes'] for r in ts]):.2f}")
    return lines


def scale_table(rows: list[dict]) -> str:
    """The markdown of :func:`run_scale_benchmark`'s rows: one table per machine, with its growth exponents."""
    out = []
    for machine in dict.fromkeys(r["machine"] for r in rows):
        mine = [r for r in rows if r["machine"] == machine]
        out += [f"Machine: {machine}; stage times in seconds.", "", *_machine_table(mine), "", *_summary_lines(mine),
                ""]
    return "\n".join(out)


def _machine_table(rows: list[dict]) -> list[str]:
    head = ("| device | views × image, maps | observed pixels | rays | " + " | ".join(STAGES)
            + " | total | peak memory | B / pixel | RMSE on well-lit texels |")
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        t = r["times"]
        mem = r["peak_rss_bytes"] / 2 ** 30
        cuda = f" (CUDA {r['cuda_peak_bytes'] / 2 ** 30:.2f})" if r.get("cuda_peak_bytes") else ""
        out.append(f"| {r['device']} | {r['views']} × {r['image']}², {r['tex']}² | {r['pixels']:,} | {r['rays']:,} | "
                   + " | ".join(f"{t.get(s, 0.0):.1f}" for s in STAGES)
                   + f" | **{t.get('total', r['wall_s']):.1f} s** | {mem:.2f} GiB{cuda} | "
                     f"{r['peak_rss_bytes'] / max(r['pixels'], 1):.0f} | "
                   + ", ".join(f"{k} {v:.4f}" for k, v in r["rmse"].items()) + " |")
    return out


def scale_figure(rows: list[dict], path) -> None:
    """Time and peak memory (log–log), one line per machine and device: above, against observed pixels over the rows
    whose maps are the size of their images; below, against texels over each texture sweep (rows of one views ×
    image with several map sizes: the same photos fitted on finer maps)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import save_figure

    pixel_rows = [r for r in rows if r["tex"] == r["image"]]
    sweeps = [k for k in dict.fromkeys((r["machine"], r["device"], r["views"], r["image"]) for r in rows)
              if len({r["tex"] for r in rows if (r["machine"], r["device"], r["views"], r["image"]) == k}) >= 2]
    series = list(dict.fromkeys([(r["machine"], r["device"]) for r in pixel_rows] + [k[:2] for k in sweeps]))
    legend_h = 0.2 * (len(series) + 1)                  # inches below the plots for one legend line per series
    height = 4.0 * (2 if sweeps else 1)
    fig, axes = plt.subplots(2 if sweeps else 1, 2, figsize=(11, height + legend_h), squeeze=False)
    # one colour per series: tab10's where they fit, tab20's twenty beyond (tab10 repeated its colours from the 11th)
    colours = plt.get_cmap("tab10" if len(series) <= 10 else "tab20").colors

    def label(machine: str, dev: str, upto_colon: bool) -> str:
        head = machine.split(" — ", 1)[0]
        cores = next((p.strip() for p in head.split(",") if "cores" in p), head)
        # the code the rows ran, as the table's caption names it (up to a colon, at most ~60 characters)
        code = machine.split(" — ", 1)[1] if " — " in machine else ""
        code = code.split(":")[0].strip() if upto_colon else code.strip()
        if len(code) > 60:
            code = code[:60].rsplit(" ", 1)[0] + " …"
        return f"{dev}, {cores}" + (f" — {code}" if code else "")

    short = [label(m, d, True) for m, d in series]
    for i, (machine, dev) in enumerate(series):
        # two earlier runs of one code (the caption up to its colon) are told apart by what follows it
        name = short[i] if short.count(short[i]) == 1 else label(machine, dev, False)
        c = colours[i % len(colours)]
        axes[0, 0].plot([], [], "o-", color=c, label=name)
        rs = sorted((r for r in pixel_rows if (r["machine"], r["device"]) == (machine, dev)), key=lambda r: r["pixels"])
        px = [r["pixels"] for r in rs]
        axes[0, 0].plot(px, [r["times"]["total"] for r in rs], "o-", color=c)
        axes[0, 0].plot(px, [r["times"].get("solve", 0.0) for r in rs], "s--", color=c)
        axes[0, 1].plot(px, [r["peak_rss_bytes"] / 2 ** 30 for r in rs], "o-", color=c)
        for key in sweeps:
            if key[:2] != (machine, dev):
                continue
            ts = sorted((r for r in rows if (r["machine"], r["device"], r["views"], r["image"]) == key),
                        key=lambda r: r["tex"])
            tex = [r["tex"] ** 2 for r in ts]
            axes[1, 0].plot(tex, [r["times"]["total"] for r in ts], "o-", color=c)
            axes[1, 0].plot(tex, [r["times"].get("solve", 0.0) for r in ts], "s--", color=c)
            axes[1, 1].plot(tex, [r["peak_rss_bytes"] / 2 ** 30 for r in ts], "o-", color=c)
            for ax, y in ((axes[1, 0], ts[-1]["times"]["total"]), (axes[1, 1], ts[-1]["peak_rss_bytes"] / 2 ** 30)):
                ax.annotate(f"{key[2]} × {key[3]}²", (tex[-1], y), textcoords="offset points", xytext=(4, 0),
                            fontsize=7, color=c, va="center")
    axes[0, 0].set(xscale="log", yscale="log", xlabel="observed pixels (maps the size of the images)",
                   ylabel="seconds", title="time (solid: total, dashed: the solve)")
    axes[0, 1].set(xscale="log", yscale="log", xlabel="observed pixels (maps the size of the images)", ylabel="GiB",
                   title="peak resident memory")
    if sweeps:
        axes[1, 0].set(xscale="log", yscale="log", xlabel="texels (the same photos on finer maps)", ylabel="seconds",
                       title="time against the map size (solid: total, dashed: the solve)")
        axes[1, 1].set(xscale="log", yscale="log", xlabel="texels (the same photos on finer maps)", ylabel="GiB",
                       title="peak resident memory against the map size")
    for ax in axes.flat:
        ax.grid(True, which="both", alpha=0.3)
    fig.legend(loc="lower center", ncol=1, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, legend_h / (height + legend_h), 1, 1))
    save_figure(fig, path)
    plt.close(fig)


def run_scale_benchmark(configs: Sequence[tuple[int, int, int]] = DEFAULT_SCALE_CONFIGS,
                        devices: Sequence[str] = ("cpu",), work=None, threads: int | None = None,
                        out: str | None = None, figure: str | None = None, rows_json: str | None = None,
                        earlier: Sequence[str] = ()) -> str:
    """Run every configuration on every device; return (and with ``out`` write into its "scale" section) the table.
    ``work``: folder for the datasets and reconstructions (kept, so a second run reuses the datasets; default a
    temporary folder); ``rows_json``: also write the rows as JSON; ``figure``: the plot's PNG; ``earlier``: JSON
    files of rows of earlier runs (``rows_json``, e.g. from a machine with a GPU) shown beside this run's — with no
    ``configs`` the table and figure are made from them alone."""
    import tempfile

    from renderer.device import resolve_device

    from ..report import atomic_write_text, replace_section

    devs = [str(resolve_device(d)) for d in devices] if configs else []
    old_rows = [r for f in earlier for r in json.loads(Path(f).read_text())]
    tmp = None if work else tempfile.TemporaryDirectory()
    root = Path(work or tmp.name)
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for views, image, tex in configs:
            for dev in devs:
                rows.append(scale_run(views, image, tex, root, dev, threads))
                r = rows[-1]
                print(f"{dev} {views} × {image}², {tex}²: {r['times']['total']:.1f} s, {r['pixels']:,} pixels, "
                      f"{r['peak_rss_bytes'] / 2 ** 30:.2f} GiB", flush=True)
                if rows_json:
                    atomic_write_text(Path(rows_json), json.dumps(rows, indent=1))
    finally:
        if tmp is not None:
            tmp.cleanup()
    rows = old_rows + rows
    if not rows:
        raise ScaleError("no configuration run and no earlier rows given: pass configs or earlier JSON files")
    text = scale_table(rows)
    if figure:
        scale_figure(rows, figure)
    if out:
        replace_section(Path(out), "scale", "## Scale: time and memory against observed pixels\n\n" + SCALE_INTRO
                        + "\n" + text)
    return text
