"""Every reader of a user's file is bounded (afm_ros.formats.user_files): a sample description
(.yaml or .json) that is a billion laughs, 5000 nested lists, binary or huge is refused at once in
one line naming the file, as parameter files and dataset specs are (test_afm_ctl, test_dataset)."""

import time

import pytest

from afm_ros.core.samples import resolve_sample

LEVEL = 'a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
LAUGHS = LEVEL + "".join(
    f"a{i}: &a{i} [{', '.join(['*a' + str(i - 1)] * 9)}]\n" for i in range(1, 9)
)


@pytest.mark.parametrize(
    "name, content, why",
    [
        ("bomb.yaml", LAUGHS.encode(), "expands to more than"),
        ("deep.yaml", b"[" * 5000 + b"]" * 5000, "nested deeper than"),
        ("deep.json", b"[" * 5000 + b"]" * 5000, "nested deeper than"),
        ("binary.yaml", bytes(range(256)) * 8, "not a text file"),
        ("huge.yaml", b"# " + b"x" * (2 << 20) + b"\n", "allowed at most 1048576 bytes"),
    ],
)
def test_a_hostile_sample_description_is_refused_in_one_line(tmp_path, name, content, why):
    path = tmp_path / name
    path.write_bytes(content)
    t0 = time.monotonic()
    with pytest.raises(ValueError) as raised:
        resolve_sample(str(path))
    text = str(raised.value)
    assert why in text and name in text and "\n" not in text, text
    assert time.monotonic() - t0 < 5.0  # refused before it is expanded, not after
