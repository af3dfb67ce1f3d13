"""The paper's numbers (Loquercio et al., RA-L 2020), by table of the paper: the one
source of every number of the paper the report prints, compares with or derives a target
from.

Each table keeps its Scenes11 column (the synthetic benchmark closest to `gld_scenes`)
as the paper prints it, each row under the name of the run (or classical method, or probe
setting) of ours it stands beside. The paper gives its own model different numbers in
different tables (Abs-Inv 0.031 in the main table and the density figure, 0.033 in the
ablation, SfM, given-pose and flow fine-tuning tables): a number is only ever read with
the table it comes from (`value`, `printed`), and `model_values` lists them.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Row:
    """A row of a table of the paper.

    Attributes:
      name: the row's name in the paper.
      printed: its Scenes11 numbers, as the paper prints them.
    """

    name: str
    printed: tuple[str, ...]

    @property
    def values(self) -> tuple[float, ...]:
        return tuple(float(number) for number in self.printed)


@dataclasses.dataclass(frozen=True)
class Table:
    """A table (or figure) of the paper, its Scenes11 column.

    Attributes:
      label: its LaTeX label in the paper, how the report names it.
      title: what it shows.
      columns: the names of a row's numbers.
      rows: our run (or method, or setting) -> the paper's row beside it.
      model: the key of the row that is the paper's model at one supervised pixel per
        image (its "Ours"), None if the table has none.
    """

    label: str
    title: str
    columns: tuple[str, ...]
    rows: dict[str, Row]
    model: str | None = None


DEPTH_COLUMNS = ("abs_inv", "abs_rel", "s_rmse")

TABLES: dict[str, Table] = {
    "results_sparse": Table(
        "tab:results_sparse",
        "the main table: one supervised pixel per image",
        DEPTH_COLUMNS,
        {
            "eigen_1px": Row("Eigen", ("0.045", "0.57", "0.77")),
            "dispnet_1px": Row("DispNet", ("0.038", "0.51", "0.70")),
            "fcrn_1px": Row("FCRN", ("0.041", "0.52", "0.74")),
            "small_encdec_1px": Row("Small Enc-Dec", ("0.046", "0.66", "0.83")),
            "struct2depth": Row("Struct2Depth", ("0.058", "0.95", "0.81")),
            "struct2depth_flow": Row("Struct2Depth + Flow", ("0.056", "0.94", "0.79")),
            "global_local_1px": Row("Ours", ("0.031", "0.43", "0.61")),
        },
        model="global_local_1px",
    ),
    "sfm_sota": Table(
        "tab:sfm_sota",
        "the comparison to SfM, with the dataset mean",
        DEPTH_COLUMNS,
        {
            "dataset_mean": Row("Dataset-Mean", ("0.069", "0.771", "0.940")),
            "global_local_1px": Row("Ours", ("0.033", "0.43", "0.61")),
        },
        model="global_local_1px",
    ),
    "ablation_studies": Table(
        "tab:ablation_studies",
        "the ablation study",
        DEPTH_COLUMNS,
        {
            # The main run's global encoder sees the flow alone: the paper's "- Image Pair"
            # row; with the image pair added back, the paper's full model.
            "global_local_image_pair": Row("Full Model", ("0.033", "0.43", "0.61")),
            "global_local_1px": Row("- Image Pair", ("0.033", "0.45", "0.62")),
            "global_local_no_coordconv": Row("- CoordConv", ("0.038", "0.52", "0.71")),
            "global_local_no_global_module": Row("- Glob. Mod.", ("0.041", "0.55", "0.73")),
            "global_local_no_flow": Row("- Flow", ("0.052", "0.73", "0.81")),
        },
        model="global_local_image_pair",
    ),
    "gt_density": Table(
        "fig:gt_density",
        "the figure of Abs-Inv against supervised pixels per image",
        ("1px", "4px", "16px", "64px", "dense"),
        {
            "global_local": Row("Ours", ("0.031", "0.028", "0.027", "0.027", "0.023")),
            "dispnet": Row("DispNet", ("0.038", "0.038", "0.033", "0.031", "0.023")),
        },
        model="global_local",
    ),
    "given_pose": Table(
        "tab:given_pose",
        "given flow, given pose",
        DEPTH_COLUMNS,
        {
            "triangulation_predicted_pose": Row("Triang.-P. Pose", ("0.061", "0.48", "0.65")),
            "triangulation_gt_pose": Row("Triang.-GT Pose", ("0.020", "0.25", "0.48")),
            "global_local_gt_flow": Row("Ours-GT Flow", ("0.015", "0.24", "0.46")),
            "global_local_gt_pose": Row("Ours-GT Pose", ("0.021", "0.28", "0.54")),
            "global_local_1px": Row("Ours", ("0.033", "0.43", "0.61")),
        },
        model="global_local_1px",
    ),
    "results_change_intrs": Table(
        "tab:results_change_intrs",
        "camera intrinsics varying by up to 20% between views",
        DEPTH_COLUMNS,
        {
            "global_local": Row("Ours", ("0.034", "0.51", "0.61")),
            "dispnet": Row("DispNet", ("0.039", "0.57", "0.70")),
        },
    ),
    "pose_experiments": Table(
        "tab:pose_experiments",
        "camera motion from the global parameters (rotation, translation: degrees)",
        ("rotation", "translation"),
        {
            "scratch_mlp": Row("Scratch-MLP", ("1.3", "74.4")),
            "pretrained_mlp": Row("Pretrained-MLP", ("0.9", "26.7")),
            "scratch_full": Row("Scratch-Full", ("0.7", "10.3")),
            "pretrained_full": Row("Pretrained-Full", ("0.7", "9.2")),
        },
    ),
    "finetune_flow": Table(
        "tab:finetune_flow",
        "fine-tuning the optical flow network",
        DEPTH_COLUMNS,
        {
            "flow_net_head": Row("PWC (*)", ("0.046", "0.63", "0.81")),
            "flow_net_finetuned": Row("Ours (finetune PWC)", ("0.038", "0.48", "0.70")),
            "flow_net_fixed": Row("Ours (no finetune)", ("0.033", "0.43", "0.61")),
        },
        model="flow_net_fixed",
    ),
}

# Where the paper gives its dataset mean (the only table that has it).
MEAN = ("sfm_sota", "dataset_mean")

# What the paper's text says beyond its tables.
TEXT = {
    # "the error increases on average by only 5% when going to sparser supervision,
    # compared to 12% for the baseline" (over its datasets).
    "density_increase_ours": 0.05,
    "density_increase_baseline": 0.12,
    # Varying intrinsics: "a small decrease in performance, of approximately 5%".
    "varying_increase_ours": 0.05,
    # "the prediction of optical flow with PWCNet requires 45 milliseconds per image pair".
    "pwc_net_ms": 45,
    # Every experiment: 256x192 pixels, about 94K iterations.
    "height": 192,
    "width": 256,
    "steps": 94_000,
}


def row(table: str, key: str) -> Row | None:
    """The paper's row of `table` beside our `key` (None if it has none)."""
    return TABLES[table].rows.get(key)


def printed(table: str, key: str) -> tuple[str, ...] | None:
    """The numbers of that row as the paper prints them (None without the row)."""
    found = row(table, key)
    return None if found is None else found.printed


def value(table: str, key: str, column: str | None = None) -> float | None:
    """One number of the paper's row of `table` beside `key`: `column` (default its first,
    Abs-Inv in the depth tables); None without the row."""
    found = row(table, key)
    if found is None:
        return None
    columns = TABLES[table].columns
    return found.values[columns.index(column) if column else 0]


def mean_value() -> float:
    """The paper's dataset mean's Abs-Inv on Scenes11."""
    return value(*MEAN)


def x_mean(table: str, key: str) -> float | None:
    """The paper's Abs-Inv of that row as a multiple of the paper's dataset mean's."""
    number = value(table, key)
    return None if number is None else number / mean_value()


def model_values() -> dict[str, float]:
    """The paper's model's Abs-Inv at one supervised pixel per image, by table."""
    return {
        key: table.rows[table.model].values[0]
        for key, table in TABLES.items()
        if table.model is not None
    }
