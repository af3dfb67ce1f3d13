"""The hand-written discussion beside a report (`discussion.md`): read, its placeholders
filled in from the results, and the report's section that shows it.

The discussion writes the suite's numbers as placeholders that the report fills in from
the results (`fill`: the kinds are `PLACEHOLDERS`), and marks any other number it quotes;
a number written by hand is an error (`fill_discussion`). Under a heading `## <target>`
it explains why that target's ordering does not hold (`discussion_section`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gld.paper import analyses as paper_analyses
from gld.paper import numbers as paper
from gld.paper import rate_check
from gld.paper.report_cells import NOT_RUN
from gld.paper.report_results import TARGETS, ReportResults

DISCUSSION = "discussion.md"
# A placeholder of the discussion: {kind:argument[:argument...]} (`fill`).
PLACEHOLDER = re.compile(r"\{(\w+):([^{}]*)\}")
# A number the discussion may not write by hand: one with a decimal point or a percent.
HAND_WRITTEN_NUMBER = re.compile(r"\d+(?:\.\d+)? ?%|\d+\.\d+")
# The placeholders' kinds and their arguments. <name>: a run of the suite, a main-table
# model's compared run (compared/<run>), a classical method (varying/<method> on the
# varying split) or triangulation_predicted_pose; numbers per test pair compare two names
# of the same split.
PLACEHOLDERS = {
    "abs_inv": "abs_inv:<name>",  # 0.0282
    "x_mean": "x_mean:<name>",  # 0.83x: Abs-Inv as a multiple of its split's dataset mean
    "change": "change:<name>:<reference>",  # +14.7%: Abs-Inv against the reference's
    "below": "below:<name>:<reference>",  # 13%: how far Abs-Inv is below the reference's
    "loss": "loss:<run>",  # 0.0298: training loss, last quarter (`rate_check.training_loss`)
    "test_at": "test_at:<run>:<step>",  # 0.0330: test Abs-Inv during training
    "worse_pairs": "worse_pairs:<name>:<reference>",  # 68%: pairs with a higher Abs-Inv
    "better_pairs": "better_pairs:<name>:<reference>",  # 62%: pairs with a lower Abs-Inv
    "paired_t": "paired_t:<name>:<reference>",  # +6.3: mean difference / its std error
    "rotation": "rotation:<run>:<setting>",  # 3.36: the pose probe's error, degrees
    "translation": "translation:<run>:<setting>",  # 65.3
    "paper": "paper:<table>:<row>[:<column>]",  # 0.031 / 0.43 / 0.61, or 0.031
    "paper_change": "paper_change:<table>:<row>:<reference>",  # +24%
    "paper_below": "paper_below:<table>:<row>:<reference>",  # 47%
    "paper_x_mean": "paper_x_mean:<table>:<row>",  # 0.45x
    "quote": "quote:<text>",  # a number from elsewhere, as written
}


def read_discussion(path: Path) -> dict[str, str]:
    """The hand-written discussion of a suite's targets: under a heading `## <key>` (a key
    of `TARGETS`), what explains that target's ordering. {} without the file."""
    if not path.exists():
        return {}
    parts = re.split(r"^## +(\S+) *$", path.read_text(), flags=re.MULTILINE)
    discussion = {key: text.strip() for key, text in zip(parts[1::2], parts[2::2], strict=True)}
    if unknown := sorted(set(discussion) - set(TARGETS)):
        raise ValueError(
            f"{path}: headings {unknown} name no target; the targets are {list(TARGETS)}"
        )
    if empty := sorted(key for key, text in discussion.items() if not text):
        raise ValueError(f"{path}: nothing under the headings {empty}")
    return discussion


def report_discussion(report: ReportResults, report_dir: Path | str) -> dict[str, str]:
    """The discussion beside a report (`<report_dir>/discussion.md`) read and filled in
    from its results: what the report shows, and what the suite checks before any task
    runs. ValueError as `read_discussion` and `fill_discussion`."""
    path = Path(report_dir) / DISCUSSION
    return fill_discussion(report, read_discussion(path), path)


def fill_discussion(
    report: ReportResults, discussion: dict[str, str], path: Path | str = DISCUSSION
) -> dict[str, str]:
    """The discussion's sections with their placeholders filled in (`fill`).

    ValueError naming every number written by hand in them (one with a decimal point
    or a percent, outside a placeholder: it would not follow the results when they
    change) and every placeholder the report cannot fill."""
    problems, filled = [], {}
    for key, text in discussion.items():
        bare = PLACEHOLDER.sub(" ", text)
        problems += [
            f"{number.group()!r} written by hand (## {key})"
            for number in HAND_WRITTEN_NUMBER.finditer(bare)
        ]
        try:
            # One line a paragraph: a filled-in line could start like a list item.
            filled[key] = re.sub(r"(?<!\n)\n(?!\n)", " ", fill(report, text))
        except ValueError as error:
            problems.append(f"{error} (## {key})")
    if problems:
        raise ValueError(
            f"{path}: " + "; ".join(problems) + ". Write the suite's numbers as "
            "placeholders ({" + "}, {".join(PLACEHOLDERS.values()) + "}) and quote any "
            "other number as {quote:...}"
        )
    return filled


def fill(report: ReportResults, text: str) -> str:
    """`text` with each placeholder replaced by the number it names, formatted as the
    report prints it (the kinds: `PLACEHOLDERS`). A run without a result gives
    "(not run yet)" or "(needs a re-run at a clean commit)"; an unknown kind, run or
    row is a ValueError."""
    return PLACEHOLDER.sub(lambda match: _placeholder(report, *match.groups()), text)


def _placeholder(report: ReportResults, kind: str, argument: str) -> str:
    if kind == "quote":  # a number from elsewhere: the paper's text, a run by hand
        return argument
    if kind not in PLACEHOLDERS:
        raise ValueError(f"unknown placeholder {{{kind}:{argument}}}")
    args = argument.split(":")
    if len(args) != PLACEHOLDERS[kind].count(":") and not kind.startswith("paper"):
        raise ValueError(f"{{{kind}:{argument}}}: not {{{PLACEHOLDERS[kind]}}}")
    if kind.startswith("paper"):
        return _paper_placeholder(kind, args)
    if kind in ("rotation", "translation"):
        result = report.results.get("pose_probe")
        if result is None:
            return f"({report.missing('pose_probe')})"
        error = result["errors"].get(args[0], {}).get(args[1])
        if error is None:
            raise ValueError(f"{{{kind}:{argument}}}: the pose probe has no such setting")
        if kind == "rotation":
            return f"{error['rotation_deg']:.2f}"
        return f"{error['translation_deg']:.1f}"
    names = args[:1] if kind in ("abs_inv", "x_mean", "loss", "test_at") else args
    named = [_named(report, name, kind, argument) for name in names]
    if kind in ("loss", "test_at") and not named[0][1].startswith("train/"):
        raise ValueError(f"{{{kind}:{argument}}}: {args[0]!r} is no training run")
    for result, task, _ in named:
        if result is None:
            return f"({report.missing(task)})"
    (first, _, varying), *rest = named
    value = first["metrics"]["abs_inv"]["mean"]
    if kind == "abs_inv":
        return f"{value:.4f}"
    if kind == "x_mean":
        mean = report.mean_reference(varying)
        return f"({NOT_RUN})" if mean is None else f"{value / mean:.2f}x"
    if kind == "loss":
        loss = rate_check.training_loss(first)
        return "—" if loss is None else f"{loss:.4f}"
    if kind == "test_at":
        steps = {int(step): test for step, test in first["curves"]["test"]}
        if int(args[1]) not in steps:
            raise ValueError(f"{{{kind}:{argument}}}: no test evaluation at that step")
        return f"{steps[int(args[1])]:.4f}"
    (second, _, other_varying) = rest[0]
    reference = second["metrics"]["abs_inv"]["mean"]
    if kind == "change":
        return f"{value / reference - 1:+.1%}"
    if kind == "below":
        return f"{1 - value / reference:.0%}"
    # Per test pair: the two runs' arrays are in the order of their split.
    if varying != other_varying:
        raise ValueError(f"{{{kind}:{argument}}}: the pairs of two splits are not joined")
    difference = np.asarray(first["abs_inv_per_example"]) - np.asarray(
        second["abs_inv_per_example"]
    )
    if kind == "worse_pairs":
        return f"{np.mean(difference > 0):.0%}"
    if kind == "better_pairs":
        return f"{np.mean(difference < 0):.0%}"
    error = difference.std(ddof=1) / np.sqrt(difference.size)
    return f"{difference.mean() / error:+.1f}"  # paired_t


def _named(
    report: ReportResults, name: str, kind: str, argument: str
) -> tuple[dict | None, str, bool]:
    """(result, its task, on the varying split) of a name in a placeholder: a run, a
    main-table model's compared run (`compared/<run>`), a classical method
    (`varying/<method>` on the varying split) or the triangulation with the probe's
    pose."""
    if name.startswith("compared/") and name.removeprefix("compared/") in report.checked:
        run = report.compared_run(name.removeprefix("compared/"))
        if run is None:  # its learning-rate check has not finished
            return None, f"train/{name.removeprefix('compared/')}", False
        return _named(report, run, kind, argument)
    if name in report.runs:
        return report.run(name), f"train/{name}", report.runs[name].varying
    varying = name.startswith("varying/")
    method = name.removeprefix("varying/")
    if method in paper_analyses.CLASSICAL:
        dataset = report.scale.varying_dataset if varying else report.scale.dataset
        return report.classical(method, varying), f"classical/{dataset.split('/')[-1]}", varying
    if name == "triangulation_predicted_pose":
        return report.results.get(name), name, False
    raise ValueError(f"{{{kind}:{argument}}}: {name!r} is no run or method of the suite")


def _paper_placeholder(kind: str, args: list[str]) -> str:
    """A placeholder of the paper's numbers (`gld.paper.numbers`)."""
    table, *keys = args
    if table not in paper.TABLES or not keys or paper.row(table, keys[0]) is None:
        raise ValueError(f"{{{kind}:{':'.join(args)}}}: no such table or row of the paper")
    if kind == "paper":
        printed = paper.printed(table, keys[0])
        if len(keys) == 1:
            return " / ".join(printed)
        columns = paper.TABLES[table].columns
        if len(keys) != 2 or keys[1] not in columns:
            raise ValueError(f"{{{kind}:{':'.join(args)}}}: the columns are {columns}")
        return printed[columns.index(keys[1])]
    if kind == "paper_x_mean":
        return f"{paper.x_mean(table, keys[0]):.2f}x"
    if len(keys) != 2 or paper.row(table, keys[1]) is None:
        raise ValueError(f"{{{kind}:{':'.join(args)}}}: not {{{PLACEHOLDERS[kind]}}}")
    value, reference = paper.value(table, keys[0]), paper.value(table, keys[1])
    if kind == "paper_change":
        return f"{value / reference - 1:+.0%}"
    return f"{1 - value / reference:.0%}"  # paper_below


def discussion_section(
    targets: Sequence[tuple[str, str, bool | None, str]], discussion: dict[str, str]
) -> str:
    """What explains each ordering that does not hold, from the hand-written discussion
    beside the report; a target without its paragraph says so."""
    failed = [(key, name) for key, name, holds, _ in targets if holds is False]
    if not failed:
        return ""
    text = (
        "\n### What we think explains the orderings that do not hold\n\n"
        f"Written by hand (`{DISCUSSION}` beside this file, one `## <target>` section each: "
        f"{', '.join(f'`{key}`' for key in TARGETS)}); its numbers of this suite's runs "
        "and of the paper's tables are filled in from the results and `gld.paper.numbers` "
        "each time the report is written, and any other number it quotes (the paper's "
        "text, another suite, a run by hand) is marked as a quote in the file.\n\n"
    )
    for key, name in failed:
        text += f"**{name}** (`{key}`). {discussion.get(key, 'Not discussed yet.')}\n\n"
    return text
