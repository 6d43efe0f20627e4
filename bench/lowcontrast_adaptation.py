"""Does an adapted tokenizer keep the contact on a low-contrast sensor?  The adaptation issue's item 5,
as one command with its table and figure.

Run:  .venv/bin/python bench/lowcontrast_adaptation.py --run runs/exp/fam_gs \
          --families runs/exp/mix_ratio/families --out runs/lowc

Targets are GelSight Mini variants whose contact response is scaled down (``response_scale``),
with camera noise and a colour cast: sensors a GelSight family tokenizer has never seen, whose
contact differs from the no-contact image by a fraction of what the families' do.  Each is adapted
with ``vqtouch adapt`` (50 shots, 400 steps, 150 held-out images, seed 0) in these arms:

- the shots alone (``--ratio 0``);
- the default mix (1:1) and the paper's 1:5, with the family the sensor is assigned to;
- the same mixes with another family forced (``--family``): what a wrong assignment, or a family
  that merged two sensor designs, does.

Every arm is scored by ``adapt`` itself on the held-out images: on the whole image and on the contact
region, beside the sensor's no-contact image (``background_*``).  The target is an adapted
tokenizer at least 2 dB above that background on the contact region.  An arm whose ``adapt.json``
exists is read, not trained again; ``lowcontrast.md`` and ``lowcontrast.png`` (the contact region's
gain over the background per arm; ``_seedN`` for ``--seed N``) are written into OUT.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

TARGETS = {
    "scale035": {"response_scale": 0.35, "noise_std": 0.01, "colour_gain": [0.95, 1.0, 1.05], "seed": 11},
    "scale015": {"response_scale": 0.15, "noise_std": 0.004, "colour_gain": [0.95, 1.0, 1.05], "seed": 12},
}
#: The contact region's gain over the no-contact background an adapted tokenizer should reach (dB).
TARGET_GAIN_DB = 2.0


def arms(other_family: int) -> list[tuple[str, list[str]]]:
    """(name, extra ``vqtouch adapt`` arguments) of every arm."""
    return [
        ("shots alone", ["--ratio", "0"]),
        ("1:1, assigned family", ["--ratio", "1"]),
        ("1:5, assigned family", ["--ratio", "5"]),
        (f"1:1, family {other_family} forced", ["--ratio", "1", "--family", str(other_family)]),
        (f"1:5, family {other_family} forced", ["--ratio", "5", "--family", str(other_family)]),
    ]


def folder_name(target: str, arm: str, seed: int = 0) -> str:
    name = f"{target}_" + arm.replace(":", "to").replace(", ", "_").replace(" ", "_")
    return name if seed == 0 else f"{name}_seed{seed}"


def run_arm(args: argparse.Namespace, target: str, extra: list[str], folder: Path) -> dict:
    from vqtouch.plugins.cli.app import main

    if not (folder / "adapt.json").is_file():
        spec = json.dumps({"name": "gelsight_mini", "variant": TARGETS[target]})
        command = ["--no-progress", "adapt", "--run", args.run, "--families", args.families, "--images", spec]
        command += ["--shots", "50", "--steps", "400", "--eval-images", "150", "--seed", str(args.seed)]
        command += ["--out", str(folder), "--overwrite"]
        if main([*command, *extra]) != 0:
            raise SystemExit(f"adapt failed for {folder.name}")
    return json.loads((folder / "adapt.json").read_text())


def row(target: str, arm: str, summary: dict) -> dict:
    after, before = summary["after"], summary["before"]
    return {
        "target": target,
        "arm": arm,
        "seed": summary["seed"],
        "family": summary["family"],
        "zero_shot_psnr": before["psnr"],
        "psnr": after["psnr"],
        "background_psnr": after["background_psnr"],
        "contact_psnr": after["contact_psnr"],
        "background_contact_psnr": after["background_contact_psnr"],
        "contact_gain_db": after["contact_psnr"] - after["background_contact_psnr"],
        "contact_fraction": after["contact_fraction"],
        "codes_used": after["codes_used"],
        "family_psnr": summary["family_held_out"]["after"]["psnr"],
    }


def write_outputs(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = [
        "| target | arm | family | whole PSNR (background) | contact PSNR (background) | contact gain dB | "
        "held-out family PSNR |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mark = "**" if r["contact_gain_db"] >= TARGET_GAIN_DB else ""
        lines.append(
            f"| {r['target']} | {r['arm']} | {r['family']} | {r['psnr']:.2f} ({r['background_psnr']:.2f}) | "
            f"{r['contact_psnr']:.2f} ({r['background_contact_psnr']:.2f}) | {mark}{r['contact_gain_db']:+.2f}{mark} | "
            f"{r['family_psnr']:.2f} |"
        )
    suffix = "" if rows[0]["seed"] == 0 else f"_seed{rows[0]['seed']}"
    (out / f"lowcontrast{suffix}.md").write_text("\n".join(lines) + "\n")
    (out / f"lowcontrast{suffix}.json").write_text(json.dumps(rows, indent=2) + "\n")
    targets = list(dict.fromkeys(r["target"] for r in rows))
    figure, axes = plt.subplots(1, len(targets), figsize=(6.5 * len(targets), 3.6), sharey=True, squeeze=False)
    for axis, target in zip(axes[0], targets):
        mine = [r for r in rows if r["target"] == target]
        axis.barh([r["arm"] for r in mine], [r["contact_gain_db"] for r in mine], color="tab:blue")
        axis.axvline(TARGET_GAIN_DB, color="tab:red", linestyle="--", label=f"target +{TARGET_GAIN_DB:g} dB")
        axis.axvline(0, color="black", linewidth=0.8)
        axis.set_title(f"{target}: contact PSNR gain over the no-contact image", fontsize=10)
        axis.set_xlabel("dB")
        axis.invert_yaxis()
    axes[0][0].legend(loc="lower right")
    figure.tight_layout()
    figure.savefig(out / f"lowcontrast{suffix}.png", dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, help="the family tokenizer (a run, checkpoint folder or bundle)")
    parser.add_argument("--families", required=True, help="a `vqtouch cluster` output of that tokenizer")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--targets", nargs="+", default=list(TARGETS), choices=list(TARGETS))
    parser.add_argument("--other-family", type=int, default=1, help="the family forced in the wrong-family arms")
    parser.add_argument("--seed", type=int, default=0, help="seed of the shots' draw and the rendered scenes")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for target in args.targets:
        for arm, extra in arms(args.other_family):
            summary = run_arm(args, target, extra, args.out / folder_name(target, arm, args.seed))
            rows.append(row(target, arm, summary))
            print(f"{target} / {arm}: contact {rows[-1]['contact_gain_db']:+.2f} dB over the background", flush=True)
    write_outputs(rows, args.out)
    print((args.out / ("lowcontrast.md" if args.seed == 0 else f"lowcontrast_seed{args.seed}.md")).read_text())


if __name__ == "__main__":
    main()
