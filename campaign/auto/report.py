"""The end of `campaign auto`: the verdict in words and RUN/auto/report.html."""

from __future__ import annotations

import html
from pathlib import Path

from campaign.auto.decisions import TIME_INPUTS, TIME_REMOVAL, inputs_text
from campaign.auto.state import AUTO_DIR, AutoResult, Round, calibrated_key, save_state
from campaign.fileio import atomic_write
from campaign.run import RunFolder


def verdict_text(run: RunFolder, state: dict) -> str:
    """The final verdict and what the user can do next, in a few lines; then each effect of time a
    round took out (campaign.auto.decisions.TIME_REMOVAL), with what it explained, unless it is in
    the final model again."""
    text = _verdict_words(run, state)
    final = set(Round.from_json(state["rounds"][-1]).effects)
    for r in map(Round.from_json, state["rounds"]):
        d = r.decision
        if d.kind == "remove_effect" and d.reason == TIME_REMOVAL and not set(r.effects) - set(d.effects) <= final:
            text += f"\n  round {r.number} took {d.effect} out: {d.text.split(': ', 1)[-1]}"
    return text


def _verdict_words(run: RunFolder, state: dict) -> str:
    last = Round.from_json(state["rounds"][-1])
    reason = (state.get("finished") or {}).get("reason")
    head = (f"{last.model} on {last.poses} poses ({last.hours:.2f} h): test-set mean {last.heldout_mm:.4f} mm "
            f"{last.ratio_text('the noise floor')}")
    if reason == "at_floor":
        return (f"verdict: at the measurement noise: nothing left to find. {head}.\n"
                f"  the model: {run.calibration_dir}/params.yaml; use it with `campaign predict {run.path}` or "
                f"`campaign compensate {run.path}`, or export it: `campaign export {run.path} --urdf OUT.urdf`")
    if reason == "unexplained":
        dep = last.signature or (f"depends on {inputs_text(last.depends_on)}" if last.depends_on else
                                 "no input found on which it depends")
        inputs = list(last.depends_on)  # all of them, ranked: a warm-up of one link is time and joints
        only_time = bool(inputs) and set(inputs) <= set(TIME_INPUTS)
        hint = ("an effect of time (drift, warm-up)" if only_time else
                f"an effect that depends on {inputs_text(inputs)}" if inputs else "an effect")
        return (f"verdict: unexplained — systematic error remains that no candidate explains: {dep}. {head}.\n"
                f"  next: write {hint} (docs/effects.md, 'Writing an effect'), add it to {run.config_path} "
                f"(effects: [..., your_file.py:YourEffect]) and run `campaign auto {run.path}` again")
    if reason in ("budget", "max_poses"):
        what = "budget" if reason == "budget" else "pose limit"
        found = last.verdict or ("at the floor" if last.floor_mm is not None else "nothing found, no noise floor yet")
        return (f"verdict: stopped at the {what} with the model {last.model} ({found} in the "
                f"last diagnosis). {head}.\n  next: run `campaign auto {run.path} "
                f"{'--budget HOURS' if reason == 'budget' else '--max-poses N'}` with a larger limit to go on")
    if reason == "no_floor":
        return (f"verdict: no missing effect found. {head}.\n  next: state the tracker's noise "
                f"(`tracker: {{noise_m: ...}}` in {run.config_path}) or measure repeats, and run auto again")
    return f"verdict: {last.decision.text}. {head}."


def result(run, state, say, *, report: bool) -> AutoResult:
    rounds = tuple(Round.from_json(r) for r in state["rounds"])
    text = verdict_text(run, state)
    page = None
    if report:
        page = write_auto_report(run, state, text)
    say(text)
    return AutoResult(run.path, rounds, rounds[-1].decision, text, page)


def write_auto_report(run: RunFolder, state: dict, text: str) -> Path:
    """RUN/calibration/report.html of the final model (calibrated again, with its report, when the
    last round's calibration wrote none; with the neural compensator after the long campaign,
    ``--select 0``, when it has the training poses for one) and RUN/auto/report.html: the story,
    one line per round, and the held-out error over the rounds against the noise floor
    (auto/rounds.png)."""
    from campaign.identify.calibrate import calibrate

    page = run.calibration_dir / "report.html"
    if not page.is_file() or page.stat().st_mtime < (run.calibration_dir / "metrics.json").stat().st_mtime:
        long = (state.get("options") or {}).get("select") == 0
        calibrate(run.path, ann="auto" if long else False, report=True, cell_segment=state.get("cell_segment"))
        state["calibrated"] = calibrated_key(run, state)
        save_state(run, state)
    rounds = [Round.from_json(r) for r in state["rounds"]]
    out = run.path / AUTO_DIR
    img = plot_rounds(rounds, out / "rounds.png")
    parts = ["<!doctype html><meta charset='utf-8'><title>campaign auto</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em}"
             "pre{background:#f6f6f6;padding:1em;white-space:pre-wrap}img{max-width:100%}</style>",
             f"<h1>campaign auto: {html.escape(run.path.name)}</h1>",
             "<h2>The rounds</h2>", f"<pre>{html.escape(chr(10).join(r.line() for r in rounds))}</pre>",
             "<h2>The verdict</h2>", f"<pre>{html.escape(text)}</pre>"]
    if img:
        parts += ["<h2>The error over the rounds</h2>", f"<img src='{img.name}'>"]
    parts += ["<p>the final model's report: <a href='../calibration/report.html'>calibration/report.html</a>; "
              "the last diagnosis: <a href='../diagnose/diagnosis.json'>diagnose/diagnosis.json</a></p>"]
    return atomic_write(out / "report.html", "\n".join(parts))


def plot_rounds(rounds, path: Path):
    """The held-out mean position error after each round (log scale) with the noise floor, each
    point labelled with the model and the poses measured; None without rounds."""
    if not rounds:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.2))
    x = [r.number for r in rounds]
    ax.plot(x, [r.heldout_mm for r in rounds], "o-", label="held-out mean ‖Δt‖ (test set)")
    floors = [r.floor_mm for r in rounds]
    if any(f for f in floors):
        ax.plot(x, [f if f else float("nan") for f in floors], ":", color="C3", label="noise floor (repeats)")
    for r in rounds:
        ax.annotate(f"{r.model.replace('geometric', 'geo')}\n{r.poses} poses", (r.number, r.heldout_mm),
                    textcoords="offset points", xytext=(0, 8), ha="center", fontsize=7)
    ax.set_yscale("log")
    values = [r.heldout_mm for r in rounds] + [f for f in floors if f]
    ax.set_ylim(min(values) / 2, max(values) * 3)
    ax.set_xlim(0.5, len(rounds) + 0.5)
    ax.set_xticks(x)
    ax.set_xlabel("round")
    ax.set_ylabel("held-out mean ‖Δt‖ [mm]")
    ax.set_title("campaign auto: the error over the rounds")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


