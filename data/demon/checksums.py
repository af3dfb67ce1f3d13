"""Published MD5 sums of DeMoN's HDF5 files, and the refusal of the leaky RGB-D files.

The sums are those of `testdata.md5` and `traindata/traindata.md5` distributed by
the DeMoN authors next to the files (https://lmb.informatik.uni-freiburg.de/data/demon/).
Every file the builder reads has a published sum; files not listed here are not checked.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

MD5_SUMS = {
    "scenes11_test.h5": "cf9314cb4229967bb9978e7e900c1a50",
    "sun3d_test.h5": "8d9d742497b6c3928bcab2f1ff14f32c",
    "rgbd_test.h5": "56393d4d56acb189c5b5e698dc8ec0ae",
    "mvs_test.h5": "f42e0ffd1243274a2fcee1ea5137176c",
    "nyu2_test.h5": "25f8f3749341b193ce507889bde122b7",
    "scenes11_train.h5": "2e07e7b76a4e39254dd046cfe6754fe7",
    "sun3d_train_0.01m_to_0.1m.h5": "ab1190b58350ed3f39b4d5e2966fb45c",
    "sun3d_train_0.1m_to_0.2m.h5": "d72b646f474559e7338a65c2199da544",
    "sun3d_train_0.2m_to_0.4m.h5": "d31bbefcffbfd795d2a19193ab61478f",
    "sun3d_train_0.4m_to_0.8m.h5": "8aeaae77e38f6493e52a0a0a7bcac8e3",
    "sun3d_train_0.8m_to_1.6m.h5": "6e872b0fec5cd5a404e25c034e1c9322",
    "sun3d_train_1.6m_to_infm.h5": "0d306ed5e6e4e4dcb5371b4c0c132e6a",
    "rgbd_bugfix_10_to_20_3d_train.h5": "3c8111feb0eebe50b5068c4a71ac6a28",
    "rgbd_bugfix_10_to_20_handheld_train.h5": "2c02bd33e6e5a7550ef5abe8eee1609e",
    "rgbd_bugfix_20_to_inf_3d_train.h5": "286c2b2bee520a427f347e848660636a",
    "rgbd_bugfix_20_to_inf_handheld_train.h5": "9a1907607af8d7543b99df33ae4d4733",
    "rgbd_10_to_20_simple_train.h5": "a316f02a84abe42ccb6a1d5450ac4bf1",
    "rgbd_20_to_inf_simple_train.h5": "0ee80f4b7450bbaa4df59854b73ca770",
}

# The first RGB-D training files (withdrawn by the DeMoN authors, their sums commented
# out in traindata.md5) contain samples of the test set.
LEAKY_MD5_SUMS = {
    "rgbd_10_to_20_3d_train.h5": "2543a4b1a2cc8385d342958b2557d25e",
    "rgbd_10_to_20_handheld_train.h5": "ee6c5805c0244b01268e394e33b4e455",
    "rgbd_20_to_inf_3d_train.h5": "5be8f60f0e1d9f5afaa3ee0afcb5e3be",
    "rgbd_20_to_inf_handheld_train.h5": "3e6c78142bfd7a92d647abf443e98e3c",
}

# rgbd_*_train.h5 without "bugfix" and other than the "simple" ones.
_LEAKY_NAME = re.compile(r"^rgbd_(?!bugfix_)(?!.*_simple_train\.h5$).*_train\.h5$")


def is_leaky_rgbd_file(file_name: str) -> bool:
    """Whether a file name is one of the old RGB-D training files that leaked test samples."""
    return bool(_LEAKY_NAME.match(file_name))


def leaky_file_message(path: str | Path) -> str:
    """The explanation given when a leaky RGB-D training file is refused."""
    name = Path(path).name
    fixed = name.replace("rgbd_", "rgbd_bugfix_", 1)
    return (
        f"{path}: refusing {name}: the first RGB-D SLAM training files of DeMoN contain "
        f"samples of rgbd_test.h5, so training on them inflates test scores. Download "
        f"{fixed} (rgbd_bugfix_train.tgz from "
        "https://lmb.informatik.uni-freiburg.de/data/demon/traindata/) and remove "
        f"{name} from the manual directory."
    )


def md5(path: str | Path, chunk_bytes: int = 1 << 24) -> str:
    """Hex MD5 of a file, read in chunks."""
    digest = hashlib.md5()
    with open(path, "rb") as stream:
        while chunk := stream.read(chunk_bytes):
            digest.update(chunk)
    return digest.hexdigest()


def verify(path: str | Path) -> None:
    """Checks a file against its published MD5 sum (files without one pass unchecked).

    Raises:
      ValueError: a leaky RGB-D file (by name or by content), or a sum that differs.
    """
    path = Path(path)
    if is_leaky_rgbd_file(path.name):
        raise ValueError(leaky_file_message(path))
    expected = MD5_SUMS.get(path.name)
    if expected is None:
        return
    actual = md5(path)
    if actual != expected:
        leaked = [name for name, value in LEAKY_MD5_SUMS.items() if value == actual]
        if leaked:
            raise ValueError(leaky_file_message(path.with_name(leaked[0])))
        raise ValueError(
            f"{path}: MD5 {actual} differs from the published {expected}; the download is "
            "incomplete or altered. Download it again, or build with verify_checksums=False "
            "to use it anyway (damaged pairs are then skipped and counted)."
        )
