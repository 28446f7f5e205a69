"""Self-contained HTML report of an evaluation run: success rates with intervals, sim-vs-real agreement
(Pearson r, MMRV), per-checkpoint curves, Beta posteriors, replay confusion matrices, rollout videos,
protocol and status counts. Plots are base64 PNGs (matplotlib, Agg); videos are base64 data URLs.

Success rates count episodes with status "ok" only; sim_error / policy_error episodes are reported
separately and never folded into failures.

Pairing checks (`pairing_warnings`): real episodes of another task than the run's are left out of every
comparison, and real or replay runs whose protocol records another initial-state grid than the run's
(`evaluation.grids.grid_info`) are flagged: each is a red banner at the top of the page and a warning
returned to the caller (`twinbench report` prints them; `strict=True` refuses to write the report).
"""

from __future__ import annotations

import base64
import html
import io
import json
import re
import subprocess
import sys
import tempfile
from collections import Counter, defaultdict
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from twinbench import __version__
from twinbench.evaluation import metrics
from twinbench.evaluation.replay import confusion_counts
from twinbench.evaluation.store import EpisodeRecord, ResultsStore

Key = tuple[str, str]  # (policy, checkpoint)

# MMRV's interval (metrics.mmrv_bootstrap), as every table labels and explains it
MMRV_RANGE = "95% re-run range"
MMRV_RANGE_NOTE = ("MMRV's range: where 95 % of the MMRVs fall that a second evaluation with as many "
                   "episodes per policy would measure if the measured success rates were the true ones "
                   "(2,000 episode resamples, seed 0). Sampling noise can only add rank violations where "
                   "the rankings agree, so the range can lie above the measured value: it says how far the "
                   "figure would move on a re-run, not where the MMRV of the true rates lies.")

VIDEO_MIME = {".mp4": "video/mp4", ".m4v": "video/mp4", ".webm": "video/webm"}
# codecs Chromium plays natively; anything else is transcoded to H.264 yuv420p
_PLAYABLE = {("video/mp4", "h264"), ("video/webm", "vp8"), ("video/webm", "vp9"), ("video/webm", "av1"),
             ("video/mp4", "av1")}


@dataclass(frozen=True)
class VideoLimits:
    """Caps on embedded videos (the page must stay loadable)."""

    max_videos: int = 12
    max_bytes_each: int = 8 * 2**20
    max_bytes_total: int = 48 * 2**20


@dataclass
class Cell:
    """Counts of one (policy, checkpoint) in one domain."""

    policy: str
    checkpoint: str
    train_step: int | None = None
    ok: int = 0
    successes: int = 0
    sim_error: int = 0
    policy_error: int = 0

    @property
    def label(self) -> str:
        return label(self.policy, self.checkpoint)

    @property
    def outcomes(self) -> list[int]:
        return [1] * self.successes + [0] * (self.ok - self.successes)

    def rate(self) -> metrics.Estimate | None:
        return metrics.rate_estimate(self.successes, self.ok) if self.ok else None


def label(policy: str, checkpoint: str) -> str:
    return f"{policy} @ {checkpoint}" if checkpoint else policy


def summarize(episodes: list[EpisodeRecord]) -> dict[Key, Cell]:
    """Group episodes by (policy, checkpoint): ok episodes, successes among them, error counts."""
    cells: dict[Key, Cell] = {}
    steps: dict[Key, Counter] = defaultdict(Counter)
    for e in episodes:
        c = cells.setdefault((e.policy, e.checkpoint), Cell(e.policy, e.checkpoint))
        if e.status == "ok":
            c.ok += 1
            c.successes += int(e.success)
        elif e.status == "sim_error":
            c.sim_error += 1
        else:
            c.policy_error += 1
        if e.train_step is not None:
            steps[(e.policy, e.checkpoint)][e.train_step] += 1
    for key, cnt in steps.items():
        cells[key].train_step = cnt.most_common(1)[0][0]
    return dict(sorted(cells.items(), key=lambda kv: (kv[0][0], _step_order(kv[1]), kv[0][1])))


def _step_order(c: Cell) -> float:
    return -1.0 if c.train_step is None else float(c.train_step)


# ---- HTML helpers ----------------------------------------------------------------------------------
def _e(x) -> str:
    return html.escape(str(x))


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f}%"


def _table(header: list[str], rows: list[list[str]], cls: str = "") -> str:
    """An HTML table; cells are pre-escaped HTML strings."""
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _note(text: str) -> str:
    return f'<p class="note">{_e(text)}</p>'


def _fig_html(fig, alt: str) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{data}">'


def _colors(policies: list[str]) -> dict[str, tuple]:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {p: cmap(i % 10) for i, p in enumerate(sorted(set(policies)))}


# ---- sections --------------------------------------------------------------------------------------
def _success_section(sim: dict[Key, Cell]) -> str:
    import matplotlib.pyplot as plt

    if not sim:
        return "<h2>Success rates (sim)</h2>" + _note("This run has no sim episodes.")
    rows = []
    for c in sim.values():
        est = c.rate()
        step = "–" if c.train_step is None else c.train_step
        if est is None:
            rows.append([_e(c.policy), _e(c.checkpoint or "–"), _e(step), "0", "0", "–", "–",
                         "–", str(c.sim_error), str(c.policy_error)])
            continue
        wl, wh = metrics.wilson(c.successes, c.ok)
        jl, jh = metrics.jeffreys(c.successes, c.ok)
        rows.append([_e(c.policy), _e(c.checkpoint or "–"), _e(step), str(c.ok), str(c.successes),
                     f"<b>{_pct(est.value)}</b>", f"[{_pct(est.low)}, {_pct(est.high)}]",
                     f"[{_pct(wl)}, {_pct(wh)}] / [{_pct(jl)}, {_pct(jh)}]", str(c.sim_error),
                     str(c.policy_error)])
    table = _table(["policy", "checkpoint", "train step", "ok episodes", "successes", "success rate",
                    "95% Clopper-Pearson", "95% Wilson / Jeffreys", "sim_error", "policy_error"], rows)
    cells = [c for c in sim.values() if c.ok]
    fig_html = ""
    if cells:
        colors = _colors([c.policy for c in cells])
        fig, ax = plt.subplots(figsize=(9, 0.45 * len(cells) + 1.2))
        y = np.arange(len(cells))[::-1]
        ests = [c.rate() for c in cells]
        vals = np.array([e.value for e in ests])
        err = np.array([[e.value - e.low for e in ests], [e.high - e.value for e in ests]])
        ax.barh(y, vals, height=0.6, color=[colors[c.policy] for c in cells], alpha=0.8)
        ax.set_ylim(-0.7, len(cells) - 0.3)
        ax.errorbar(vals, y, xerr=err, fmt="none", ecolor="black", capsize=4, lw=1.2)
        ax.set_yticks(y, [f"{c.label} (n={c.ok})" for c in cells])
        ax.set_xlim(0, 1)
        ax.set_xlabel("success rate (sim), 95% Clopper-Pearson interval")
        ax.grid(axis="x", alpha=0.3)
        fig_html = _fig_html(fig, "success rate per policy with 95% intervals")
    return ("<h2>Success rates (sim)</h2><p>Success rate = successes / episodes with status ok. "
            "Intervals are two-sided 95%.</p>" + table + fig_html)


def _sim_real_section(sim: dict[Key, Cell], real: dict[Key, Cell], real_source: str) -> str:
    import matplotlib.pyplot as plt

    head = "<h2>Sim vs real</h2>"
    if not real:
        return head + _note(f"No real outcomes found ({real_source}): import them with "
                            "`twinbench import-real FILE.csv` to compare sim with real.")
    keys = [k for k in sim if k in real and sim[k].ok and real[k].ok]
    if not keys:
        return head + _note(f"Real outcomes exist ({real_source}) but none share a policy and checkpoint "
                            f"with this run's sim episodes. Real: {', '.join(label(*k) for k in real)}; "
                            f"sim: {', '.join(label(*k) for k in sim) or 'none'}.")
    s = np.array([sim[k].successes / sim[k].ok for k in keys])
    r = np.array([real[k].successes / real[k].ok for k in keys])
    stats_rows = []
    try:
        pr = metrics.pearson(sim=s, real=r)
        r_text = f"{pr.r:.3f} [{pr.low:.3f}, {pr.high:.3f}]"
        stats_rows.append(["Pearson r (95% Fisher-z interval)", r_text])
    except ValueError as err:
        r_text = "undefined"
        stats_rows.append(["Pearson r", f"undefined: {_e(err)}"])
    mm = metrics.mmrv_bootstrap(sim=[sim[k].outcomes for k in keys], real=[real[k].outcomes for k in keys],
                                n_boot=2000, seed=0)
    stats_rows.append([f"MMRV [{MMRV_RANGE}]", f"{mm.value:.3f} [{mm.low:.3f}, {mm.high:.3f}]"])
    stats_rows.append(["paired policy/checkpoints", str(len(keys))])
    if len(keys) < 2:
        stats_rows.append(["note", "MMRV needs at least two policies to rank; with one it is 0."])
    fig, ax = plt.subplots(figsize=(6.5, 6))
    colors = _colors([k[0] for k in keys])
    for k in keys:
        es, er = sim[k].rate(), real[k].rate()
        ax.errorbar(es.value, er.value, xerr=[[es.value - es.low], [es.high - es.value]],
                    yerr=[[er.value - er.low], [er.high - er.value]], fmt="o", color=colors[k[0]],
                    capsize=3, lw=1, ms=7)
        ax.annotate(label(*k), (es.value, er.value), textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.plot([0, 1], [0, 1], "--", color="gray", lw=1, label="y = x")
    ax.set_xlim(-0.03, 1.03)
    ax.set_ylim(-0.03, 1.03)
    ax.set_aspect("equal")
    ax.set_xlabel("sim success rate")
    ax.set_ylabel("real success rate")
    ax.set_title(f"Pearson r = {r_text}, MMRV = {mm.value:.3f}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    rows = [[_e(label(*k)), f"{sim[k].successes}/{sim[k].ok}", _pct(s[i]),
             f"{real[k].successes}/{real[k].ok}", _pct(r[i]), f"{100 * (s[i] - r[i]):+.1f} pp"]
            for i, k in enumerate(keys)]
    missing = [label(*k) for k in sim if k not in keys]
    extra = ""
    if missing:
        extra = _note(f"Sim entries without real outcomes (not in r / MMRV): {', '.join(missing)}.")
    extra += _note(MMRV_RANGE_NOTE)
    return (head + f"<p>Real outcomes from {_e(real_source)}. Error bars: 95% Clopper-Pearson on both "
            "axes.</p>"
            + _table(["statistic", "value"], stats_rows, "kv") + _fig_html(fig, "sim vs real success rates")
            + _table(["policy", "sim k/n", "sim rate", "real k/n", "real rate", "sim − real"], rows) + extra)


def _curves_section(sim: dict[Key, Cell], real: dict[Key, Cell]) -> str:
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    head = "<h2>Success across training iterations</h2>"
    policies = sorted({c.policy for c in list(sim.values()) + list(real.values())
                       if c.train_step is not None and c.ok})
    if not policies:
        return head + _note("No episode has a train_step, so there are no per-checkpoint curves.")
    ncol = min(3, len(policies))
    nrow = -(-len(policies) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.4 * nrow), squeeze=False)
    for ax, policy in zip(axes.ravel(), policies, strict=False):
        for cells, name, style in ((sim, "sim", "o-"), (real, "real", "s--")):
            pts = sorted((c.train_step, c.rate()) for c in cells.values()
                         if c.policy == policy and c.train_step is not None and c.ok)
            if not pts:
                continue
            x = np.array([p[0] for p in pts], dtype=float)
            v = np.array([p[1].value for p in pts])
            lo = np.array([p[1].low for p in pts])
            hi = np.array([p[1].high for p in pts])
            line = ax.plot(x, v, style, label=name, ms=5)[0]
            if name == "sim":
                ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)
            else:
                ax.errorbar(x, v, yerr=[v - lo, hi - v], fmt="none", ecolor=line.get_color(), capsize=3)
        ax.set_title(policy, fontsize=10)
        ax.set_ylim(-0.03, 1.03)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=5, integer=True, min_n_ticks=2))
        ax.xaxis.set_major_formatter(FuncFormatter(_step_label))  # 20k, not 20000: labels never collide
        ax.set_xlabel("train step")
        ax.set_ylabel("success rate")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax in axes.ravel()[len(policies):]:
        ax.axis("off")
    fig.tight_layout()
    return (head + "<p>Sim: line with 95% Clopper-Pearson band; real: dashed with 95% interval bars.</p>"
            + _fig_html(fig, "success rate across training iterations"))


def _step_label(value: float, _pos=None) -> str:
    """A compact train-step tick label: 500, 20k, 1.5M."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:.3g}{suffix}"
    return f"{value:.3g}"


def _posterior_section(sim: dict[Key, Cell], real: dict[Key, Cell], max_pairs: int = 12) -> str:
    import matplotlib.pyplot as plt

    head = "<h2>Posteriors</h2>"
    keys = [k for k, c in sim.items() if c.ok]
    if not keys:
        return head + _note("No sim episodes with status ok: no posteriors to show.")
    grid = np.linspace(0, 1, 401)
    fig, ax = plt.subplots(figsize=(min(14.0, max(4.0, 1.0 * len(keys) + 2)), 4.2))
    has_real = False
    for i, k in enumerate(keys):
        halves = [("sim", sim[k], -1, "tab:blue")]
        if k in real and real[k].ok:
            halves.append(("real", real[k], 1, "tab:orange"))
            has_real = True
        for _, c, side, color in halves:
            post = metrics.beta_posterior(c.successes, c.ok)
            dens = post.pdf(grid)
            w = 0.4 * dens / dens.max()
            if len(halves) == 1:
                ax.fill_betweenx(grid, i - w, i + w, color=color, alpha=0.6, lw=0)
            else:
                ax.fill_betweenx(grid, i, i + side * w, color=color, alpha=0.6, lw=0)
            ax.plot([i - 0.15, i + 0.15] if len(halves) == 1 else sorted([i, i + side * 0.15]),
                    [post.mean()] * 2, color="black", lw=1.5)
    ax.set_xticks(range(len(keys)), [label(*k) for k in keys], rotation=30, ha="right", fontsize=8)
    ax.set_xlim(-0.8, len(keys) - 0.2)
    ax.set_ylim(0, 1)
    ax.set_ylabel("success probability")
    ax.grid(axis="y", alpha=0.3)
    handles = [plt.Rectangle((0, 0), 1, 1, color="tab:blue", alpha=0.6)]
    names = ["sim posterior" + (" (left half)" if has_real else "")]
    if has_real:
        handles.append(plt.Rectangle((0, 0), 1, 1, color="tab:orange", alpha=0.6))
        names.append("real posterior (right half)")
    ax.legend(handles, names, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    out = (head + "<p>Beta(1 + k, 1 + n − k) posteriors of each success probability (uniform prior); "
           "black bars mark posterior means.</p>" + _fig_html(fig, "Beta posterior violins"))
    shown = keys[:max_pairs]
    if len(shown) >= 2:
        rows = []
        for a in shown:
            ca = sim[a]
            row = [f"<b>{_e(label(*a))}</b>"]
            for b in shown:
                if a == b:
                    row.append("–")
                    continue
                p = metrics.prob_greater(ca.successes, ca.ok, sim[b].successes, sim[b].ok)
                row.append(f'<span class="{"hi" if p > 0.95 else "lo" if p < 0.05 else ""}">{p:.3f}</span>')
            rows.append(row)
        out += ("<p>P(row policy's sim success probability &gt; column's), exact under the posteriors "
                "above:</p>" + _table([""] + [_e(label(*b)) for b in shown], rows, "matrix"))
        if len(keys) > max_pairs:
            out += _note(f"Only the first {max_pairs} of {len(keys)} entries are compared.")
    return out


def pair_replay(replay: list[EpisodeRecord], real: list[EpisodeRecord]):
    """Pair replay and real episodes by (policy, checkpoint, init_state); when several share that key,
    by seed as well. Only status-ok episodes pair. Returns (pairs, unpaired_replay, unpaired_real)."""
    rp, rl = defaultdict(list), defaultdict(list)
    for e in replay:
        if e.status == "ok":
            rp[(e.policy, e.checkpoint, e.init_state)].append(e)
    for e in real:
        if e.status == "ok":
            rl[(e.policy, e.checkpoint, e.init_state)].append(e)
    replayed = {k[:2] for k in rp}  # real episodes of policies never replayed are not "unpaired"
    pairs, n_rp, n_rl = [], 0, 0
    for key in sorted(set(rp) | {k for k in rl if k[:2] in replayed}):
        a, b = rp.get(key, []), rl.get(key, [])
        if len(a) == 1 and len(b) == 1:
            pairs.append((a[0], b[0]))
            continue
        by_seed = {e.seed: e for e in b}
        matched = [(e, by_seed[e.seed]) for e in a if e.seed in by_seed]
        pairs += matched
        n_rp += len(a) - len(matched)
        n_rl += len(b) - len(matched)
    return pairs, n_rp, n_rl


def _confusion_html(pairs) -> str:
    c = confusion_counts((rep.success, rl.success) for rep, rl in pairs)
    m = np.array([[c.tp, c.fn], [c.fp, c.tn]])  # [real success?][replay success?], index 0 = success
    n, agree = c.n, c.accuracy

    def cell(v):
        return f'<td style="background: rgba(31,119,180,{0.1 + 0.6 * v / max(n, 1):.2f})">{v}</td>'

    return ('<table class="confusion"><tr><th></th><th>replay success</th><th>replay failure</th></tr>'
            f"<tr><th>real success</th>{cell(m[0, 0])}{cell(m[0, 1])}</tr>"
            f"<tr><th>real failure</th>{cell(m[1, 0])}{cell(m[1, 1])}</tr></table>"
            f'<p class="small">{n} paired episodes, agreement {_pct(agree) if n else "–"}</p>')


def _replay_section(sources: list[tuple[str, list[EpisodeRecord], list[EpisodeRecord], str]]) -> str:
    """sources: (run id, its replay episodes, the real episodes they pair with, where those come from)."""
    head = "<h2>Replay vs real</h2>"
    if not sources:
        return head + _note("No replay episodes (domain \"replay\") in the runs of this report.")
    pairs, notes = [], []
    for src, replay, real, real_from in sources:
        if not real:
            notes.append(f"Run {src!r}: {len(replay)} replay episodes but no real outcomes to pair with.")
            continue
        got, n_rp, n_rl = pair_replay(replay, real)
        pairs += got
        if n_rp or n_rl:
            notes.append(f"Run {src!r}: {n_rp} replay and {n_rl} real ok episodes ({real_from}) found no "
                         "partner.")
        n_err = sum(e.status != "ok" for e in replay)
        if n_err:
            notes.append(f"Run {src!r}: {n_err} replay episodes ended in sim_error/policy_error and are "
                         "not paired.")
    if not pairs:
        return head + "".join(_note(t) for t in notes) + _note(
            "No replay episode shares (policy, checkpoint, init_state) with a real one.")
    groups = defaultdict(list)
    for p in pairs:
        groups[(p[0].policy, p[0].checkpoint)].append(p)
    blocks = [f'<div class="cm"><h3>all policies</h3>{_confusion_html(pairs)}</div>']
    blocks += [f'<div class="cm"><h3>{_e(label(*k))}</h3>{_confusion_html(v)}</div>'
               for k, v in sorted(groups.items())]
    where = "; ".join(f"replay episodes of run {s!r} paired with real outcomes from {f}"
                      for s, _, r, f in sources if r)
    return (head + "<p>Real rollouts' commanded actions replayed open-loop in the twin from the same initial "
            "states; episodes paired by policy, checkpoint and initial state (and seed when several). "
            f"{_e(where)}.</p>"
            + '<div class="cms">' + "".join(blocks) + "</div>" + "".join(_note(t) for t in notes))


def _probe_codec(path: Path) -> tuple[str | None, str | None]:
    """(codec, pixel format) of the first video stream, read from ffmpeg's banner (imageio-ffmpeg)."""
    import imageio_ffmpeg

    res = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-i", str(path)],
                         capture_output=True, text=True, timeout=30)
    m = re.search(r"Video: (\w+)[^,]*, (\w+)", res.stderr)
    return (m.group(1), m.group(2)) if m else (None, None)


def _transcode_h264(path: Path, out: Path) -> None:
    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error", "-y", "-i", str(path),
           "-an", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-vf", "scale=trunc(iw/2)*2:trunc(ih/2)*2",
           "-movflags", "+faststart", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    if res.returncode != 0:
        raise RuntimeError(res.stderr.strip()[-300:])


def _video_section(episodes: list[EpisodeRecord], limits: VideoLimits, video_root: Path) -> str:
    head = "<h2>Rollout videos</h2>"
    with_video = [e for e in episodes if e.video_path]
    if not with_video:
        return head + _note("No episode of this run has a video.")
    order = {"sim": 0, "replay": 1, "real": 2}
    with_video.sort(key=lambda e: (order[e.domain], e.policy, e.checkpoint, e.init_state, e.seed))
    items, notes, total = [], [], 0
    with tempfile.TemporaryDirectory(prefix="twinbench-report-") as tmp:
        for e in with_video:
            if len(items) >= limits.max_videos:
                notes.append(f"{len(with_video) - len(items) - len(notes)} more videos not embedded "
                             f"(cap: {limits.max_videos} videos).")
                break
            path = Path(e.video_path)
            if not path.is_absolute() and not path.is_file() and (video_root / path).is_file():
                path = video_root / path  # relative to the store's folder rather than the cwd
            if not path.is_file():
                notes.append(f"missing video file {path}")
                continue
            mime = VIDEO_MIME.get(path.suffix.lower())
            codec, pix_fmt = _probe_codec(path)
            src = path
            if codec is None:
                notes.append(f"{path}: no video stream found")
                continue
            # Chromium decodes H.264 only in 4:2:0 (yuv420p); other codecs/containers are transcoded
            if (mime, codec) not in _PLAYABLE or (codec == "h264" and pix_fmt != "yuv420p"):
                src, mime = Path(tmp) / f"v{len(items)}.mp4", "video/mp4"
                try:
                    _transcode_h264(path, src)
                except (RuntimeError, subprocess.TimeoutExpired) as err:
                    notes.append(f"{path}: could not transcode {codec} to H.264: {err}")
                    continue
            size = src.stat().st_size
            if size > limits.max_bytes_each or total + size > limits.max_bytes_total:
                notes.append(f"{path} ({_size(size)}) not embedded: size cap {_size(limits.max_bytes_each)} "
                             f"each, {_size(limits.max_bytes_total)} in all.")
                continue
            total += size
            data = base64.b64encode(src.read_bytes()).decode("ascii")
            outcome = e.status if e.status != "ok" else "success" if e.success else "failure"
            caption = (_e(f"{e.domain}: {label(e.policy, e.checkpoint)}, init state {e.init_state}, "
                          f"seed {e.seed}") + f' — <b class="{outcome}">{outcome}</b>')
            items.append(f'<figure><video controls muted loop preload="auto" '
                         f'src="data:{mime};base64,{data}"></video><figcaption>{caption}</figcaption></figure>')
    return (head + f"<p>{len(items)} of {len(with_video)} episode videos embedded "
            f"({_size(total)}).</p>" + '<div class="videos">' + "".join(items) + "</div>"
            + "".join(_note(t) for t in notes))


def _size(n: int) -> str:
    return f"{n / 2**20:.1f} MiB" if n >= 2**20 else f"{n / 2**10:.0f} KiB"


def _status_section(groups: list[tuple[str, list[EpisodeRecord]]]) -> str:
    rows = []
    for name, eps in groups:
        cells = summarize(eps)
        for c in cells.values():
            rows.append([_e(name), _e(c.label), str(c.ok), str(c.sim_error), str(c.policy_error),
                         str(c.ok + c.sim_error + c.policy_error)])
    if not rows:
        return "<h2>Episode status</h2>" + _note("No episodes.")
    return ("<h2>Episode status</h2><p>Errored episodes are excluded from success rates, never counted "
            "as failures.</p>"
            + _table(["source", "policy", "ok", "sim_error", "policy_error", "total"], rows))


def _value_html(v, depth: int = 0) -> str:
    if isinstance(v, dict) and v and depth < 3:
        return _table(["key", "value"], [[_e(k), _value_html(x, depth + 1)] for k, x in v.items()], "kv")
    text = json.dumps(v, indent=None if len(json.dumps(v)) < 100 else 1, default=str)
    if len(text) > 4000:
        text = text[:4000] + f" … ({len(text)} characters in all)"
    return f"<code>{_e(text)}</code>"


def _protocol_section(run_id: str, protocol: dict | None, episodes: list[EpisodeRecord],
                      real_run_id: str | None, real_protocol: dict | None) -> str:
    out = "<h2>Protocol</h2>"
    if protocol is None:
        out += _note(f"Run {run_id!r} has episodes but no registered protocol (start_run was not called).")
    else:
        out += f"<h3>run {_e(run_id)}</h3>" + _value_html(protocol)
    sim = [e for e in episodes if e.domain == "sim"]
    if sim:
        inits = sorted({e.init_state for e in sim})
        seeds = sorted({e.seed for e in sim})
        out += _table(["recorded in the store", "value"], [
            ["tasks", _e(", ".join(sorted({e.task for e in sim})))],
            ["sim episodes", str(len(sim))],
            ["initial states used", f"{len(inits)}: {_e(_compact(inits))}"],
            ["seeds used", f"{len(seeds)}: {_e(_compact(seeds))}"],
            ["success rule", _e(_rule_counts(sim))],
            ["mean episode steps / wall time", f"{np.mean([e.steps for e in sim]):.0f} steps / "
                                               f"{np.mean([e.wall_time_s for e in sim]):.2f} s"],
        ], "kv")
    if real_run_id and real_protocol is not None:
        out += f"<h3>real run {_e(real_run_id)}</h3>" + _value_html(real_protocol)
    return out


def _rule_counts(episodes: list[EpisodeRecord]) -> str:
    """'final: 12, early: 4': which success rule judged how many episodes ('final' = full-length episode
    judged on its last frames, the reference rule; 'early' = ended when the criterion first held)."""
    counts: dict[str, int] = {}
    for e in episodes:
        rule = str((e.metrics or {}).get("success_rule", "not recorded"))
        counts[rule] = counts.get(rule, 0) + 1
    return ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))


def _compact(ints: list[int]) -> str:
    """[0, 1, 2, 5, 7, 8] -> '0-2, 5, 7-8'."""
    parts, start = [], None
    for i, v in enumerate(ints):
        if start is None:
            start = v
        if i + 1 == len(ints) or ints[i + 1] != v + 1:
            parts.append(str(start) if start == v else f"{start}-{v}")
            start = None
    return ", ".join(parts)


_CSS = """
body { font-family: -apple-system, 'Segoe UI', Roboto, 'DejaVu Sans', sans-serif; margin: 0 auto;
       max-width: 1180px; padding: 16px 28px 48px; color: #1d2125; line-height: 1.45; }
h1 { margin-bottom: 4px; } h2 { border-bottom: 2px solid #dde3ea; padding-bottom: 4px; margin-top: 36px; }
table { border-collapse: collapse; margin: 10px 0; font-size: 13px; }
th, td { border: 1px solid #d5dbe1; padding: 4px 8px; text-align: left; vertical-align: top; }
th { background: #f1f4f7; } table.kv td:first-child { font-weight: 600; background: #fafbfc; }
table.matrix td { text-align: center; } .hi { color: #0a7a2f; font-weight: 600; } .lo { color: #b3261e; }
.warn { background: #fdecea; border: 2px solid #b3261e; color: #6b0f0a; padding: 8px 12px; font-size: 15px;
        font-weight: 600; margin: 10px 0; }
.note { background: #fff8e1; border-left: 4px solid #f4b400; padding: 6px 10px; font-size: 14px; }
.meta { color: #5f6b76; font-size: 13px; } .small { font-size: 12px; color: #5f6b76; margin: 2px 0; }
img { max-width: 100%; display: block; margin: 8px 0; }
.cms { display: flex; flex-wrap: wrap; gap: 18px; } .cm h3 { font-size: 14px; margin: 8px 0 2px; }
table.confusion td { text-align: center; min-width: 70px; font-weight: 600; }
.videos { display: flex; flex-wrap: wrap; gap: 14px; }
figure { margin: 0; width: 360px; } video { width: 360px; background: #000; }
figcaption { font-size: 12px; } .success { color: #0a7a2f; } .failure { color: #b3261e; }
.sim_error, .policy_error { color: #8a5a00; }
code { font-size: 12px; white-space: pre-wrap; word-break: break-word; }
"""


def pairing_warnings(task: str, protocol: dict | None, real_eps: list[EpisodeRecord],
                     other_protocols: dict[str, dict | None]) -> tuple[list[str], list[EpisodeRecord]]:
    """(warnings, the real episodes of `task`): real episodes of other tasks are dropped with a warning;
    a run in `other_protocols` ({run id: protocol}) whose recorded grid differs from `protocol`'s (the
    evaluated run's) is warned about (its init_state values index other states)."""
    out = []
    others = Counter((e.domain, e.task) for e in real_eps if e.task != task)
    if others:
        what = ", ".join(f"{n} {d} of task {t!r}" for (d, t), n in sorted(others.items()))
        out.append(f"episodes of another task are left out of every comparison: {what} (this run is task "
                   f"{task!r}); import the real outcomes of {task!r} under their own --real-run-id")
    grid = (protocol or {}).get("grid")
    for rid, other in other_protocols.items():
        theirs = (other or {}).get("grid")
        if not isinstance(grid, dict) or not isinstance(theirs, dict):
            continue
        if theirs.get("task", task) == task and theirs.get("id") != grid.get("id"):
            out.append(f"run {rid!r} indexes another initial-state grid than this run (grid "
                       f"{theirs.get('id')}, {theirs.get('n_states')} states, vs {grid.get('id')}, "
                       f"{grid.get('n_states')} states): init_state values do not name the same states; pair "
                       "them through an index map (import-real / replay --index-map) or evaluate on the "
                       "same grid")
    return out, [e for e in real_eps if e.task == task]


def write_report(store: ResultsStore, run_id: str, out: str | Path, real_run_id: str | None = None,
                 videos: VideoLimits | None = None, replay_run_id: str | None = None, *,
                 strict: bool = False, warn=None) -> Path:
    """Write the HTML report of `run_id` to `out`; returns the path.

    Real or replay episodes that do not pair with the run (another task or grid, see `pairing_warnings`)
    are flagged in a banner and passed to `warn(message)`; with `strict` they raise ValueError instead.

    Real outcomes: episodes with domain "real" in `run_id` and `real_run_id`. Replay episodes: domain
    "replay" in `run_id`, `replay_run_id` and `real_run_id`, each paired with the real episodes of its
    own run when it has some (as `twinbench replay` records them), else with the real outcomes above."""
    import matplotlib

    matplotlib.use("Agg")
    runs = store.runs()
    if run_id not in runs:
        raise ValueError(f"run {run_id!r} not found in {store.path}; known runs: {runs or 'none'}")
    videos = videos or VideoLimits()
    episodes = store.episodes(run_id)
    protocol = _protocol_or_none(store, run_id)
    sim_eps = [e for e in episodes if e.domain == "sim"]
    real_eps = [e for e in episodes if e.domain == "real"]
    sources = [f"run {run_id!r}"] if real_eps else []
    real_protocol = None
    if real_run_id and real_run_id != run_id:
        if real_run_id in runs:
            own = {(e.policy, e.checkpoint, e.init_state, e.seed) for e in real_eps}
            real_eps += [e for e in store.episodes(real_run_id, domain="real")
                         if (e.policy, e.checkpoint, e.init_state, e.seed) not in own]
            sources.append(f"run {real_run_id!r}")
            real_protocol = _protocol_or_none(store, real_run_id)
        else:
            sources.append(f"run {real_run_id!r} is not in the store")
    real_source = ", ".join(sources) if sources else "no real run given"
    replay_sources, replay_eps = [], []
    for src in dict.fromkeys(r for r in (run_id, replay_run_id, real_run_id) if r and r in runs):
        rp = store.episodes(src, domain="replay")
        if rp:
            own_real = store.episodes(src, domain="real")
            replay_sources.append((src, rp, own_real or real_eps,
                                   f"run {src!r}" if own_real else real_source))
            replay_eps += rp
    task = protocol.get("task") if isinstance(protocol, dict) and "task" in protocol else (
        ", ".join(sorted({e.task for e in sim_eps or episodes})) or "?")
    linked = [real_run_id] if real_protocol is not None else []
    linked += [src for src, *_ in replay_sources if src != run_id]
    other_protocols = {r: _protocol_or_none(store, r) for r in dict.fromkeys(linked)}
    warnings, real_eps = pairing_warnings(task, protocol, real_eps + [e for _, rp, _, _ in replay_sources
                                                                      for e in rp], other_protocols)
    real_eps = [e for e in real_eps if e.domain == "real"]
    replay_sources = [(src, [e for e in rp if e.task == task], [e for e in rl if e.task == task], frm)
                      for src, rp, rl, frm in replay_sources]
    replay_eps = [e for e in replay_eps if e.task == task]
    if warnings and strict:
        raise ValueError(f"real/replay episodes do not pair with run {run_id!r}: " + "; ".join(warnings))
    for w in warnings:
        (warn or (lambda m: None))(w)
    sim, real = summarize(sim_eps), summarize(real_eps)
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    status_groups = [(f"{run_id} / sim", sim_eps), ("replay", replay_eps), ("real", real_eps)]
    body = [
        f"<h1>twinbench report — {_e(run_id)}</h1>",
        f'<p class="meta">task {_e(task)} · {len(sim_eps)} sim, {len(replay_eps)} replay, '
        f"{len(real_eps)} real episodes · store {_e(store.path)} · generated {now} by twinbench "
        f"{__version__} · Python {sys.version.split()[0]}</p>",
        *(f'<div class="warn">Warning: {_e(w)}</div>' for w in warnings),
        _success_section(sim),
        _sim_real_section(sim, real, real_source),
        _curves_section(sim, real),
        _posterior_section(sim, real),
        _replay_section(replay_sources),
        _video_section(sim_eps + replay_eps + real_eps, videos, store.path.parent),
        _status_section([g for g in status_groups if g[1]]),
        _protocol_section(run_id, protocol, episodes, real_run_id, real_protocol),
    ]
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>twinbench report — {_e(run_id)}</title><link rel=\"icon\" href=\"data:,\">"
            f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(page, encoding="utf-8")
    return out


def _protocol_or_none(store: ResultsStore, run_id: str) -> dict | None:
    try:
        return store.run_protocol(run_id)
    except KeyError:
        return None
