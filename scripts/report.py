"""The calibration report: DIR/index.html and the PNGs it shows, from a calibration file, its
per-pose residuals (the CSV ftcal-calibrator writes beside it) and optionally the twin's truth.

Every number on the page is read from those files; nothing is copied by hand. Run through
scripts/report, which picks Debian's python3 (numpy, matplotlib, python3-protobuf) and finds the
generated calibration_pb2.py in the build tree.
"""
import argparse
import csv
import html
import math
import os
import sys
import tempfile

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from google.protobuf import text_format  # noqa: E402

import calibration_pb2  # noqa: E402  (generated; scripts/report puts it on sys.path)

COMPONENTS = ["fx (N)", "fy (N)", "fz (N)", "tx (N m)", "ty (N m)", "tz (N m)"]
VARIANTS = ["naive tare", "without T~", "full calibration"]


class ReportError(Exception):
    pass


def read_calibration(path):
    cal = calibration_pb2.Calibration()
    try:
        with open(path, encoding="utf-8") as f:
            text_format.Parse(f.read(), cal)
    except OSError as e:
        raise ReportError(f"{path}: {e.strerror}")
    except text_format.ParseError as e:
        raise ReportError(f"{path}: {e}")
    if len(cal.leg) == 0:
        raise ReportError(f"{path}: no legs in the calibration")
    return cal


def read_residuals(path):
    """{variant: array (poses x 6)} from pose,variant,fx_n,...,tz_nm rows."""
    out = {v: [] for v in VARIANTS}
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None or header[:2] != ["pose", "variant"] or len(header) != 8:
                raise ReportError(f"{path}: header is not pose,variant,fx_n,...,tz_nm")
            for line, row in enumerate(reader, start=2):
                if len(row) != 8:
                    raise ReportError(f"{path}:{line}: {len(row)} fields, expected 8")
                if row[1] not in out:
                    raise ReportError(f"{path}:{line}: unknown variant '{row[1]}'")
                try:
                    values = [float(x) for x in row[2:]]
                except ValueError:
                    raise ReportError(f"{path}:{line}: a value is not a number")
                out[row[1]].append(values)
    except OSError as e:
        raise ReportError(f"{path}: {e.strerror}")
    for v in VARIANTS:
        if not out[v]:
            raise ReportError(f"{path}: no rows for '{v}'")
        out[v] = np.array(out[v])
    return out


WALK_VARIANTS = ["naive tare", "full calibration", "truth"]
WALK_STYLE = {"naive tare": dict(color="tab:red", lw=0.7, alpha=0.8),
              "full calibration": dict(color="tab:blue", lw=0.9),
              "truth": dict(color="black", lw=0.7, ls="--")}
# "truth" is the same readings corrected with the true parameters: the error of a calibration
# apart from the sensors' own noise.
WALK_LABEL = {"truth": "true parameters"}


def read_walking(path):
    """(columns, {variant: array (samples x (1 + 42))}) from the calibrator's <cal>.walking.csv:
    t_s, variant, then fx..tz for each leg and the total."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None or header[:2] != ["t_s", "variant"] or (len(header) - 2) % 6 != 0:
                raise ReportError(f"{path}: header is not t_s,variant,<LEG>_fx_n,...")
            out = {}
            for line, row in enumerate(reader, start=2):
                if len(row) != len(header):
                    raise ReportError(f"{path}:{line}: {len(row)} fields, expected {len(header)}")
                if row[1] not in WALK_VARIANTS:
                    raise ReportError(f"{path}:{line}: unknown variant '{row[1]}'")
                try:
                    out.setdefault(row[1], []).append([float(row[0])] + [float(x) for x in row[2:]])
                except ValueError:
                    raise ReportError(f"{path}:{line}: a value is not a number")
    except OSError as e:
        raise ReportError(f"{path}: {e.strerror}")
    for v in ("naive tare", "full calibration"):
        if v not in out:
            raise ReportError(f"{path}: no rows for '{v}'")
    groups = [header[2 + 6 * g].rsplit("_", 2)[0] for g in range((len(header) - 2) // 6)]
    return groups, {v: np.array(rows) for v, rows in out.items()}


def plot_walking(groups, walk, outdir):
    """The report's Fig. 9: every ground-contact wrench in W during the walk, naive tare against
    the calibration (and the truth's correction when given)."""
    n = len(groups)
    fig, axes = plt.subplots(6, n, figsize=(2.3 * n, 11), sharex=True, sharey="row")
    for g, name in enumerate(groups):
        for i in range(6):
            ax = axes[i, g]
            for v in WALK_VARIANTS:
                if v in walk:
                    ax.plot(walk[v][:, 0], walk[v][:, 1 + 6 * g + i], label=WALK_LABEL.get(v, v),
                            **WALK_STYLE[v])
            if i == 0:
                ax.set_title(name)
            if g == 0:
                ax.set_ylabel(COMPONENTS[i])
            if i == 5:
                ax.set_xlabel("t (s)")
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle("Ground-contact wrenches in W during the walk (about the CoM)")
    fig.tight_layout()
    return save(fig, outdir, "walking.png")


def walking_rows(groups, walk, weight_n):
    """rms per component: against the truth's correction when there is one, else the total's
    residual against (0, 0, G, 0, 0, 0) (the walk is quasi-static)."""
    rows = []
    if "truth" in walk:
        ref = walk["truth"]
        for v in ("naive tare", "full calibration"):
            d = walk[v][:, 1:] - ref[:, 1:]
            legs = d[:, : 6 * (len(groups) - 1)].reshape(len(d), -1, 6)
            rows.append([v, "legs - true parameters'"] + [fmt(x, 3) for x in np.sqrt((legs ** 2).mean(axis=(0, 1)))])
            tot = d[:, 6 * (len(groups) - 1):]
            rows.append([v, "total - true parameters'"] + [fmt(x, 3) for x in np.sqrt((tot ** 2).mean(axis=0))])
    else:
        target = np.array([0.0, 0.0, weight_n, 0.0, 0.0, 0.0])
        for v in ("naive tare", "full calibration"):
            tot = walk[v][:, 1 + 6 * (len(groups) - 1):] - target
            rows.append([v, "total - (0,0,G,0,0,0)"] + [fmt(x, 3) for x in np.sqrt((tot ** 2).mean(axis=0))])
    return rows


def save(fig, outdir, name):
    """Atomic: a temporary file in DIR renamed onto the name."""
    fd, tmp = tempfile.mkstemp(dir=outdir, suffix=".png.tmp")
    os.close(fd)
    fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
    os.chmod(tmp, 0o644)  # mkstemp makes it 0600; the report is for everyone to read
    os.replace(tmp, os.path.join(outdir, name))
    return name


def plot_residual_violins(res, outdir):
    """One axis per panel (variant x component): the naive tare's residuals are tens of times
    the calibration's, and on a shared axis the calibrated violins would be flat lines."""
    labels = {"naive tare": "naive tare", "without T~": "without T~ (step 1 only)",
              "full calibration": "full calibration"}
    fig, axes = plt.subplots(len(VARIANTS), 6, figsize=(15, 7.5))
    for r, v in enumerate(VARIANTS):
        for i in range(6):
            ax = axes[r, i]
            ax.violinplot([res[v][:, i]], showmedians=True)
            ax.set_xticks([])
            ax.axhline(0.0, color="gray", lw=0.5)
            ax.tick_params(labelsize=7)
            if r == 0:
                ax.set_title(COMPONENTS[i], fontsize=9)
            if i == 0:
                ax.set_ylabel(labels[v], fontsize=8)
    fig.suptitle("Residual of the total wrench at the CoM in W, per steady pose "
                 "(each panel its own scale)")
    fig.tight_layout()
    return save(fig, outdir, "residuals_violin.png")


def leg_table_rows(cal):
    """The report's Table II per leg: value +- sigma of every per-leg estimate."""
    def pm(v, s, scale=1.0, digits=4):
        return f"{fmt(scale * v, digits)} ± {fmt(scale * s, 2)}"
    rows = []
    for leg in cal.leg:
        f, t = leg.force_offset_n, leg.torque_offset_nm
        r, p = leg.mounting.rotation_vector_deg, leg.mounting.p_tilde_prime_m
        rows.append([leg.name] + [pm(getattr(f, a), getattr(f, "sigma_" + a)) for a in "xyz"]
                    + [pm(getattr(t, a), getattr(t, "sigma_" + a)) for a in "xyz"]
                    + [pm(leg.leg_weight_n.value, leg.leg_weight_n.sigma)]
                    + [pm(getattr(r, a), getattr(r, "sigma_" + a)) for a in "xyz"]
                    + [pm(getattr(p, a), getattr(p, "sigma_" + a), 1e3) for a in "xyz"]
                    + [leg.saturated_samples, leg.saturated_poses])
    return rows


LEG_TABLE_HEADER = (["leg"] + [f"f_o {a} (N)" for a in "xyz"] + [f"τ_o {a} (N m)" for a in "xyz"]
                    + ["m g (N)"] + [f"R̃ {a} (deg)" for a in "xyz"]
                    + [f"p̃' {a} (mm)" for a in "xyz"] + ["saturated samples", "saturated poses"])

GLOSSARY = [
    ("T̃ = (R̃, p̃)", "the mounting error of a transducer: its true pose in the body frame is "
     "T̃ times the nominal one (design files). R̃ is shown as a rotation vector; p̃' = "
     "R̃ᵀ(p̃ + p^C_B) is what step 2 estimates. T̃ acts about the body origin, so a tilt alone "
     "makes p̃' about a centimetre."),
    ("s (s⁺, s⁻)", "small misalignments of the transducer against gravity in the hanging "
     "series (the report's eq. 4-7): s⁺ the mean of the two series of a pair, s⁻ half their "
     "difference."),
    ("phase φ", "where a leg is in its rotation: φ = θ / 2π wrapped to [0, 1), θ the shaft "
     "angle, 0 with the leg straight down. The leg's CoM r(φ) is a function of it."),
    ("naive tare", "the baseline: offsets = the reading with all feet in the air, no leg "
     "gravity model, nominal mounting."),
    ("without T~", "step 1 only (offsets, leg weights and CoM from hanging), nominal mounting."),
    ("robot CoM: fixed / leg-aware", "the balance target of step 2: about a fixed C (the "
     "report), or about the CoM as it moves with the legs (m_k, r_k(φ) from step 1)."),
    ("BIC, ΔBIC", "P ln(RSS/P) + DOF ln P over the P standing poses; lowest wins, ΔBIC is a "
     "row's distance from the winner."),
    ("noise floor", "what the poses' own within-pose scatter lets the residual be; a residual "
     "far above it means the model misses something the data sees."),
]


def hanging_stats(cal):
    """{(leg, variant): ResidualStats} with variant in 'with s', 'without s', 'naive tare'."""
    out = {}
    for r in cal.hanging_residual:
        leg, _, variant = r.label.partition(" ")
        out[(leg, variant)] = r
    return out


def plot_hanging_residuals(cal, outdir):
    stats = hanging_stats(cal)
    legs = [leg.name for leg in cal.leg]
    variants = ["naive tare", "without s", "with s"]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    width = 0.27
    x = np.arange(len(legs))
    for i, ax in enumerate(axes.flat):
        for j, v in enumerate(variants):
            rms = [stats[(leg, v)].rms[i] if (leg, v) in stats else np.nan for leg in legs]
            ax.bar(x + (j - 1) * width, rms, width, label=v)
        ax.set_xticks(x)
        ax.set_xticklabels(legs)
        ax.set_title("rms " + COMPONENTS[i])
        ax.set_yscale("log")
    axes.flat[0].legend(fontsize=8)
    fig.suptitle("Hanging residuals (reading minus model) per leg")
    fig.tight_layout()
    return save(fig, outdir, "hanging_residuals.png")


def sinusoid(fit, phi):
    return fit.a_m * np.sin(2 * np.pi * phi + fit.c_rad) + fit.d_m


def plot_com(cal, truth, outdir):
    names = []
    phi = np.linspace(0.0, 1.0, 400)
    for k, leg in enumerate(cal.leg):
        com = leg.com
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
        bins = [com.bin_x_m, com.bin_y_m, com.bin_z_m]
        sig = [com.bin_sigma_x_m, com.bin_sigma_y_m, com.bin_sigma_z_m]
        fitted = [sinusoid(com.x, phi), np.full_like(phi, com.y_m.value), sinusoid(com.z, phi)]
        true_leg = truth.leg[k] if truth is not None and k < len(truth.leg) else None
        for i, ax in enumerate(axes):
            if len(com.bin_phase) and len(bins[i]) == len(com.bin_phase):
                yerr = np.array(sig[i]) * 1e3 if len(sig[i]) == len(com.bin_phase) else None
                ax.errorbar(np.array(com.bin_phase), np.array(bins[i]) * 1e3, yerr=yerr, fmt=".",
                            ms=2, lw=0.5, color="tab:blue", label="bins (median, spread)")
            ax.plot(phi, fitted[i] * 1e3, color="tab:red", label="fit")
            if true_leg is not None and true_leg.HasField("com"):
                tc = true_leg.com
                t = [sinusoid(tc.x, phi), np.full_like(phi, tc.y_m.value), sinusoid(tc.z, phi)][i]
                ax.plot(phi, t * 1e3, "k--", lw=0.8, label="truth")
            ax.set_xlabel("phase")
            ax.set_ylabel(["x", "y", "z"][i] + " (mm)")
        axes[0].legend(fontsize=7)
        fig.suptitle(f"Leg {leg.name}: CoM r(phase) in ft")
        fig.tight_layout()
        names.append(save(fig, outdir, f"com_{leg.name}.png"))
    return names


def estimates(cal):
    """[(name, value, sigma)] of every scalar estimate, in a fixed order."""
    out = []
    for leg in cal.leg:
        n = leg.name
        for field, unit in (("force_offset_n", "N"), ("torque_offset_nm", "N m")):
            e = getattr(leg, field)
            for ax in "xyz":
                out.append((f"{n} {field} {ax}", getattr(e, ax), getattr(e, "sigma_" + ax), unit))
        out.append((f"{n} leg_weight_n", leg.leg_weight_n.value, leg.leg_weight_n.sigma, "N"))
        if leg.HasField("mounting"):
            for field, unit, scale in (("rotation_vector_deg", "deg", 1.0),
                                       ("p_tilde_prime_m", "mm", 1e3)):
                e = getattr(leg.mounting, field)
                if not leg.mounting.HasField(field):
                    continue
                for ax in "xyz":
                    out.append((f"{n} {field} {ax}", scale * getattr(e, ax),
                                scale * getattr(e, "sigma_" + ax), unit))
    if cal.HasField("p_c_b_m"):
        for ax in "xyz":
            out.append((f"p_c_b_m {ax}", 1e3 * getattr(cal.p_c_b_m, ax),
                        1e3 * getattr(cal.p_c_b_m, "sigma_" + ax), "mm"))
    return out


def plot_vs_truth(est, tru, outdir):
    truth = {name: value for name, value, _, _ in tru}
    rows = [(name, (v - truth[name]) / s) for name, v, s, _ in est
            if name in truth and s > 0 and math.isfinite(v)]
    if not rows:
        return None
    fig, ax = plt.subplots(figsize=(12, 4))
    z = np.array([r[1] for r in rows])
    ax.plot(np.arange(len(z)), z, ".")
    for y in (-2, 2):
        ax.axhline(y, color="gray", lw=0.5, ls="--")
    ax.set_ylabel("(estimate - truth) / sigma")
    ax.set_xlabel("parameter (table order)")
    ax.set_title(f"Estimates against the truth: {np.mean(np.abs(z) <= 2) * 100:.0f}% within 2 sigma")
    fig.tight_layout()
    return save(fig, outdir, "vs_truth.png")


def correlation_of(cal):
    """(names, n x n array) of the step-2 correlation in the calibration file, or None."""
    if not cal.HasField("correlation"):
        return None
    c = cal.correlation
    n = len(c.parameter)
    if n == 0 or len(c.value) != n * n:
        raise ReportError(f"correlation: {len(c.value)} values for {n} parameters "
                          f"(expected {n * n})")
    return list(c.parameter), np.array(c.value, dtype=float).reshape(n, n)


def strongest_correlations(names, r, per_group=3):
    """Per leg (and "shared" for p^C_B): the `per_group` off-diagonal pairs of largest |rho|
    with at least one parameter of that leg, as [group, a, b, rho] rows, strongest first."""
    groups = []
    for n in names:
        g = n.split(" ")[0] if not n.startswith("p^C_B") else "shared"
        if g not in groups:
            groups.append(g)
    def group_of(n):
        return "shared" if n.startswith("p^C_B") else n.split(" ")[0]
    rows = []
    for g in groups:
        pairs = [(abs(r[i, j]), i, j) for i in range(len(names)) for j in range(i + 1, len(names))
                 if g in (group_of(names[i]), group_of(names[j]))]
        pairs.sort(key=lambda x: -x[0])
        for _, i, j in pairs[:per_group]:
            rows.append([g, names[i], names[j], f"{r[i, j]:+.3f}"])
    return rows


def plot_correlation(names, r, outdir):
    fig, ax = plt.subplots(figsize=(9, 8))
    im = ax.imshow(r, vmin=-1, vmax=1, cmap="RdBu_r")
    ax.set_xticks(range(len(names)))
    ax.set_yticks(range(len(names)))
    ax.set_xticklabels(names, rotation=90, fontsize=6)
    ax.set_yticklabels(names, fontsize=6)
    fig.colorbar(im, ax=ax, label="correlation")
    ax.set_title("Correlation of the step-2 estimates (sandwich covariance)")
    fig.tight_layout()
    return save(fig, outdir, "correlation.png")


def leg_map_rows(cal):
    """Per transducer: the rms torque misfit against each leg's shaft (calibration's
    leg_map_check), the own shaft first."""
    m = cal.leg_map_check
    n = len(cal.leg)
    if len(m.rms_nm) != n * n:
        return []
    rows = []
    for k, leg in enumerate(cal.leg):
        rms = m.rms_nm[n * k:n * (k + 1)]
        own = rms[k]
        other = min(rms[j] for j in range(n) if j != k)
        rows.append([leg.name] + [fmt(x, 3) for x in rms] + [f"{other / own:.1f}" if own > 0 else "-"])
    return rows


def table(header, rows):
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>"
                   for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def fmt(x, digits=4):
    return f"{x:.{digits}g}" if math.isfinite(x) else "nan"


def main():
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("calibration")
    p.add_argument("residuals")
    p.add_argument("outdir")
    p.add_argument("--truth")
    p.add_argument("--walking", help="the calibrator's <cal>.walking.csv (Fig. 9)")
    p.add_argument("--health", help="ftcal-doctor's text of the recording")
    a = p.parse_args()
    try:
        cal = read_calibration(a.calibration)
        res = read_residuals(a.residuals)
        truth = read_calibration(a.truth) if a.truth else None
        walking = read_walking(a.walking) if a.walking else None
    except ReportError as e:
        print(f"report: {e}", file=sys.stderr)
        return 2
    os.makedirs(a.outdir, exist_ok=True)

    imgs = [plot_residual_violins(res, a.outdir), plot_hanging_residuals(cal, a.outdir)]
    com_imgs = plot_com(cal, truth, a.outdir)
    try:
        corr = correlation_of(cal)
    except ReportError as e:
        print(f"report: {a.calibration}: {e}", file=sys.stderr)
        return 2
    corr_img = plot_correlation(*corr, a.outdir) if corr is not None else None
    est = estimates(cal)
    tru = estimates(truth) if truth is not None else None
    vs = plot_vs_truth(est, tru, a.outdir) if tru is not None else None

    truth_by_name = {n: v for n, v, _, _ in tru} if tru is not None else {}
    est_header = ["parameter", "estimate", "± sigma", "unit"] + (["truth", "(est-truth)/sigma"]
                                                               if tru is not None else [])
    est_rows = []
    for name, v, s, unit in est:
        row = [name, fmt(v), fmt(s, 2), unit]
        if tru is not None:
            t = truth_by_name.get(name, float("nan"))
            row += [fmt(t), fmt((v - t) / s, 2) if s > 0 else "-"]
        est_rows.append(row)

    model_rows = [["*" if r.selected else "", calibration_pb2.StandingModel.Name(r.model),
                   "leg-aware" if r.leg_aware_com else "fixed", r.dof,
                   fmt(r.cv_mse), fmt(r.rss), fmt(r.bic), f"{r.delta_bic:.1f}"]
                  for r in cal.model_selection]
    margin = ""
    if cal.solver.HasField("bic_margin"):
        margin = (f"<p>Selected by a BIC margin of {cal.solver.bic_margin:.1f} over "
                  f"{html.escape(cal.solver.runner_up)}")
        if cal.solver.HasField("com_bic_margin"):
            margin += (f"; {cal.solver.com_bic_margin:.1f} over the best candidate with the other "
                       "robot-CoM model")
        margin += ".</p>"
    mass_and_floor = ""
    if cal.HasField("mass_check"):
        m = cal.mass_check
        mass_and_floor += (f"<p>Total mass: configured {m.configured_kg:.4f} kg, implied by the "
                           f"data {m.implied_kg:.4f} ± {m.sigma_kg:.4f} kg (allowed difference "
                           f"{m.allowed_kg:.4f} kg): "
                           f"{'consistent' if m.consistent else 'MISMATCH (accepted)'}.</p>")
    if cal.HasField("noise_floor") and cal.noise_floor.HasField("residual_to_floor"):
        nf = cal.noise_floor
        mass_and_floor += (f"<p>Standing residual: {nf.residual_to_floor:.2f} times the noise "
                           f"floor of the poses (warn above {nf.warn_factor:g}); floor rms "
                           + ", ".join(f"{c} {fmt(x, 2)}" for c, x in zip(COMPONENTS, nf.floor_rms))
                           + ".</p>")
    def change(a, b):
        return f"{100.0 * (b - a) / a:+.0f}%" if a > 0 else "-"
    rmse_rows = [[r.samples, r.wrench, r.reference, r.count, fmt(r.force_naive_n, 3),
                  fmt(r.force_calibrated_n, 3), change(r.force_naive_n, r.force_calibrated_n),
                  fmt(r.torque_naive_nm, 3), fmt(r.torque_calibrated_nm, 3),
                  change(r.torque_naive_nm, r.torque_calibrated_nm)] for r in cal.result_rmse]
    warnings = "".join(f"<p><b>Warning:</b> {html.escape(w)}</p>" for w in cal.warning)
    res_rows = [[r.label, r.count] + [fmt(x, 3) for x in r.rms] for r in cal.standing_residual]
    hang_rows = [[r.label, r.count] + [fmt(x, 3) for x in r.rms] for r in cal.hanging_residual]
    prov = cal.provenance
    prov_rows = [["input", f"{i.path} ({i.bytes} bytes, sha256 {i.sha256})"] for i in prov.input]
    prov_rows += [["config", f"{prov.config_path} (sha256 {prov.config_sha256})"],
                  ["software", prov.software_version], ["created", prov.created_utc],
                  ["host", prov.host], ["command", prov.command_line]]

    def img(name):
        return f'<img src="{html.escape(name)}" alt="{html.escape(name)}">'

    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>ftcal calibration report</title>",
        "<style>body{font-family:sans-serif;max-width:1250px;margin:auto}"
        "table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ccc;"
        "padding:2px 6px;font-size:13px;text-align:right}img{max-width:100%}</style></head><body>",
        f"<h1>Calibration of {html.escape(cal.robot_name)}</h1>",
        f"<p>Selected model <b>{calibration_pb2.StandingModel.Name(cal.model)}</b> from "
        f"{cal.standing_poses} steady poses.</p>",
        "<p>Method: profile " + html.escape(cal.solver.profile or "?") + "; step-2 solver "
        + html.escape(cal.solver.solver) + "; hanging rotations "
        + ("exact" if cal.solver.exact_hanging_rotations else "first-order (report)")
        + "; hanging gravity prior " + ("on" if cal.solver.hanging_gravity_prior else "off")
        + "; robot CoM " + ("leg-aware" if cal.solver.leg_aware_com else "fixed (report)")
        + " (" + html.escape(cal.solver.com_model_source or "?") + ").</p>",
        warnings,
        mass_and_floor,
        "<h2>Residuals of the total wrench at the CoM (W)</h2>", img(imgs[0]),
        table(["variant", "poses"] + ["rms " + c for c in COMPONENTS], res_rows),
        "<h2>Ground-contact RMSE: naive tare against the calibration (the journal's terms)</h2>",
        table(["samples", "wrench", "against", "count", "force naive (N)", "force calibrated (N)",
               "change", "torque naive (N m)", "torque calibrated (N m)", "change"], rmse_rows)
        if rmse_rows else "",
        "<h2>Model selection (the report's Table I)</h2>",
        "<p>One table for the robot, not one per leg: the residual of step 2 is the summed "
        "wrench of the six legs against the balance target, so its CV error and BIC do not "
        "split into legs. The selected model gives every leg the parameters below (Table II); "
        "how the legs' estimates depend on each other is in the correlation further down.</p>",
        table(["selected", "model", "robot CoM", "DOF", "CV MSE", "RSS", "BIC", "ΔBIC"],
              model_rows), margin,
        "<h2>Estimates per leg (the report's Table II; ± 1 σ)</h2>",
        table(LEG_TABLE_HEADER, leg_table_rows(cal)),
        "<h2>Estimates" + (" and truth" if tru is not None else "") + "</h2>",
        table(est_header, est_rows),
    ]
    if vs:
        parts.append(img(vs))
    if corr is not None:
        parts += ["<h2>Correlation of the estimates</h2>",
                  "<p>From the sandwich covariance the step-2 σ come from, for the selected "
                  "model's parameters (R~ as the rotation-vector perturbation, p~' or p^C_B). "
                  "Step 1's σ are spreads over leg cycles and have no joint covariance. "
                  "Strongest pairs per leg:</p>",
                  table(["leg", "parameter", "parameter", "correlation"],
                        strongest_correlations(*corr)),
                  img(corr_img)]
    if cal.HasField("leg_map_check") and leg_map_rows(cal):
        m = cal.leg_map_check
        parts += ["<h2>Leg map check</h2>",
                  f"<p>Each transducer's standing torques fitted as those of a foot turning "
                  f"with each leg's shaft, over {m.poses} poses: rms misfit (N m); the own "
                  f"shaft must fit best (refused when another fits {m.ratio_limit:g} times "
                  f"better). "
                  + ("Consistent." if m.consistent else "<b>MISMATCH (accepted).</b>") + "</p>",
                  table(["transducer"] + [f"shaft {leg.name}" for leg in cal.leg]
                        + ["best other / own"], leg_map_rows(cal))]
    if a.health:
        with open(a.health, encoding="utf-8") as f:
            parts += ["<h2>Recording health (ftcal-doctor, before the calibration)</h2>",
                      "<pre>" + html.escape(f.read()) + "</pre>"]
    if cal.recording_gaps:
        parts.append("<h2>Recording</h2>")
        lossy = [g for g in cal.recording_gaps if g.lost or g.restarts]
        total = sum(g.received + g.lost for g in cal.recording_gaps if g.used)
        if not lossy:
            parts.append(f"<p>No transducer record missing: {total} records in the phases "
                         "used, every RDT sequence number present.</p>")
        else:
            parts += [f"<p>Transducer records missing by RDT sequence number, per phase and "
                      f"channel ({total} records in the phases used); a phase used is refused "
                      "above calibrator.max_gap_share unless --allow-gaps.</p>",
                      table(["phase", "session", "channel", "used", "received", "lost",
                             "lost share", "restarts"],
                            [[g.phase, g.session_id, g.channel, "yes" if g.used else "no",
                              g.received, g.lost, f"{100.0 * g.lost_share:.2f}%", g.restarts]
                             for g in lossy])]
    parts += ["<h2>Hanging residuals per leg (with and without s)</h2>", img(imgs[1]),
              table(["series", "samples"] + ["rms " + c for c in COMPONENTS], hang_rows),
              "<h2>Leg CoM against phase (bins and fit)</h2>"] + [img(n) for n in com_imgs]
    if walking is not None:
        groups, walk = walking
        parts += ["<h2>Walking: ground-contact wrenches, calibration against naive tare</h2>",
                  img(plot_walking(groups, walk, a.outdir)),
                  table(["variant", "rms of"] + COMPONENTS,
                        walking_rows(groups, walk, cal.total_mass_kg * cal.g0_m_s2))]
    parts += ["<h2>Glossary</h2>",
              "<dl>" + "".join(f"<dt><b>{html.escape(t)}</b></dt><dd>{html.escape(d)}</dd>"
                               for t, d in GLOSSARY) + "</dl>"]
    parts += ["<h2>Provenance</h2>", table(["", ""], prov_rows), "</body></html>"]

    fd, tmp = tempfile.mkstemp(dir=a.outdir, suffix=".html.tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write("\n".join(parts))
        f.flush()
        os.fsync(f.fileno())
    os.chmod(tmp, 0o644)
    os.replace(tmp, os.path.join(a.outdir, "index.html"))
    print(os.path.join(a.outdir, "index.html"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
