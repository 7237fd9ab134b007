"""The README's figures of the committed demo run, generated from that run's own files.

The paragraph between `<!-- demo-figures -->` and `<!-- /demo-figures -->` in README.md is this
module's output for `docs/results/demo/` (verdict.json, scores.json, report.md); a test fails when
the two disagree, so the README never quotes a run other than the one committed beside it.

    python -m cps_experiments.readme_figures          # print the paragraph
    python -m cps_experiments.readme_figures --write  # put it into README.md
"""

import argparse
import json
import os
import re
import sys

START, END = "<!-- demo-figures -->", "<!-- /demo-figures -->"
REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), *[".."] * 5))
DEMO_DIR = os.path.join(REPO, "docs", "results", "demo")
README = os.path.join(REPO, "README.md")


def _ended_by(report_text):
    """'done after 73 s of mission (110 s wall time ...)' from the report's 'ended by' line, or ''."""
    match = re.search(r"^- ended by: (.+)$", report_text, re.M)
    return match.group(1).strip() if match else ""


def demo_paragraph(demo_dir=DEMO_DIR):
    """The README paragraph on the committed demo run in `demo_dir`."""
    with open(os.path.join(demo_dir, "verdict.json")) as stream:
        verdict = json.load(stream)
    with open(os.path.join(demo_dir, "scores.json")) as stream:
        scores = json.load(stream)
    with open(os.path.join(demo_dir, "report.md")) as stream:
        ended = _ended_by(stream.read())
    failures = verdict.get("failures", [])
    reasons = "".join(f"\n  - {reason}" for reason in failures)
    return (
        f"The committed run of `make demo` ([docs/results/demo/](docs/results/demo/report.md)), four robots "
        f"across the shaped link: {ended or 'its end not recorded'}. Its verdict is **{verdict['status']}**{':' if failures else '.'}"
        f"{reasons}\n\n"
        f"The fused map against the simulator's ground truth at {scores['resolution_m']:g} m: voxel for voxel "
        f"**F1 {scores['f1_exact']:.3f}** (precision {scores['precision_exact']:.3f}, recall "
        f"{scores['recall_exact']:.3f}); within ±1 voxel in all 26 directions, F1 "
        f"{scores['f1_within_1_voxel']:.3f} (precision {scores['precision_within_1_voxel']:.3f}, recall "
        f"{scores['recall_within_1_voxel']:.3f}); {100 * scores['coverage_within_1_voxel']:.1f} % of the observable "
        f"surface ({scores['observable_voxels']} voxels; the surface from: {scores['observable_from']}) found within ±1 voxel. "
        f"Link use, per-cloud latency and the map server's counts per robot are in its report."
    )


def readme_section(readme_text):
    """The text between the markers in README.md; ValueError if they are missing."""
    start, end = readme_text.find(START), readme_text.find(END)
    if start < 0 or end < start:
        raise ValueError(f"README.md has no {START} ... {END} section")
    return readme_text[start + len(START) : end].strip()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="replace the section in README.md")
    args = parser.parse_args(argv)
    paragraph = demo_paragraph()
    if not args.write:
        print(paragraph)
        return 0
    with open(README) as stream:
        text = stream.read()
    readme_section(text)  # the markers must be there
    start, end = text.find(START), text.find(END)
    with open(README, "w") as stream:
        stream.write(text[: start + len(START)] + "\n" + paragraph + "\n" + text[end:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
