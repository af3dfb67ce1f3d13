"""The launchers' flags made from option fields (`experiments.common.define_option_flags`):
their types, bounds and launcher defaults, and their values read back."""

import pytest
from absl import flags
from option_checks import Example

from experiments import common
from gld import options


def test_flags_are_made_from_the_options_with_their_types_and_bounds():
    flag_set = flags.FlagValues()
    common.define_option_flags(options.option_fields(Example), {"count": 5}, flag_set)
    flag_set(["prog", "--rate=0.25", "--widths=2,3", "--kind=b", "--switch"])
    assert common.option_flag_values(options.option_fields(Example), flag_set) == {
        "rate": 0.25,
        "count": 5,  # the launcher's default
        "kind": "b",
        "widths": [2, 3],
        "extras": [],
        "switch": True,
    }  # "choice" left at None is omitted
    assert flag_set["rate"].help == "A rate."
    for bad in ("--rate=0", "--rate=2", "--count=0", "--kind=c"):
        fresh = flags.FlagValues()
        common.define_option_flags(options.option_fields(Example), flag_set=fresh)
        with pytest.raises(flags.IllegalFlagValueError):
            fresh(["prog", bad])


def test_a_list_flag_of_words_is_named():
    flag_set = flags.FlagValues()
    common.define_option_flags(options.option_fields(Example), flag_set=flag_set)
    flag_set(["prog", "--widths=4,wide"])
    with pytest.raises(ValueError, match=r"widths must be integers, got \['4', 'wide'\]"):
        common.option_flag_values(options.option_fields(Example), flag_set)


def test_a_launcher_default_must_name_an_option():
    with pytest.raises(ValueError, match="coutn"):
        common.define_option_flags(options.option_fields(Example), {"coutn": 2}, flags.FlagValues())
