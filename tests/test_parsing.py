"""Reading what users write: a key given twice, a document nested too deeply and numbers with an
exponent, in mission files (YAML and JSON) and a run's config.json."""

from __future__ import annotations

import pytest

from roverswarm.cli import main
from roverswarm.config import config_from_json
from roverswarm.env.missions import load_mission, parse_mission_text
from roverswarm.errors import UserError
from roverswarm.parsing import load_text

MISSION = """name: twice
rovers:
  start: [[-0.8, -0.8], [0.8, -0.8]]
pois:
  - {{position: [0.0, 0.5]{radius}}}
{more}"""


@pytest.mark.parametrize(
    "text, line",
    [
        (MISSION.format(radius=", radius: 0.1, radius: 0.5", more=""), "line 5: 'radius' is given twice"),
        (MISSION.format(radius="", more="pois:\n  - {position: [0.5, 0.5]}\n"), "line 6: 'pois' is given twice"),
    ],
)
def test_a_mission_key_given_twice_is_refused_with_its_line(text, line, tmp_path, capsys):
    """PyYAML keeps the last of two equal keys: a second ``pois:`` dropped the first list."""
    with pytest.raises(UserError, match=f"mission file 'm.yaml': {line}"):
        parse_mission_text(text, "m.yaml")
    path = tmp_path / "m.yaml"
    path.write_text(text)
    assert main(["mission", "run", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert line in err and err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_a_json_key_given_twice_is_refused():
    with pytest.raises(UserError, match="mission file 'm.json': 'pois' is given twice in one object"):
        parse_mission_text('{"pois": [], "pois": [{"position": [0, 0]}]}', "m.json")


@pytest.mark.parametrize("kind, text", [("YAML", "[" * 5000 + "]" * 5000), ("JSON", "[" * 100_000)])
def test_a_document_nested_too_deeply_is_one_error(kind, text):
    with pytest.raises(UserError, match="nested too deeply|is not valid"):
        load_text(text, kind, "file 'f'")
    with pytest.raises(UserError, match="config.json is not a roverswarm training config"):
        config_from_json("[" * 100_000)


@pytest.mark.parametrize("kind", ["YAML", "JSON"])
def test_an_integer_longer_than_python_converts_is_one_error(kind):
    with pytest.raises(
        UserError, match=r"file 'f' is not valid (YAML|JSON): Exceeds the limit \(4300 digits\)"
    ) as error:
        load_text('{"radius": ' + "9" * 5000 + "}", kind, "file 'f'")
    assert "set_int_max_str_digits" not in str(error.value)


@pytest.mark.parametrize("suffix", ["json", "yaml"])
def test_a_mission_file_with_a_byte_order_mark_reads_as_without(suffix, tmp_path):
    text = '{"rovers": {"start": [[0, 0]]}, "pois": [{"position": [0.5, 0.5]}]}'
    plain, marked = tmp_path / f"plain.{suffix}", tmp_path / f"marked.{suffix}"
    plain.write_text(text, encoding="utf-8")
    marked.write_text(text, encoding="utf-8-sig")
    assert marked.read_bytes().startswith(b"\xef\xbb\xbf")
    marked_params, plain_params = load_mission(marked).params, load_mission(plain).params
    for field in ("fixed_pois", "fixed_starts", "observe_radius"):
        assert (getattr(marked_params, field) == getattr(plain_params, field)).all(), field


def test_numbers_with_an_exponent_read_as_numbers_and_the_rest_as_before():
    """YAML 1.1 reads 3e-4 and 1.0e5 as strings; JSON and YAML 1.2 as numbers."""
    text = "a: 3e-4\nb: 1.0e5\nc: -2E+1\nd: .5e1\ne: 1e\nf: 0x10\ng: 1_000\nh: e5\ni: '3e-4'\nj: 2.5\n"
    assert load_text(text, "YAML", "f") == {
        "a": 3e-4, "b": 1e5, "c": -20.0, "d": 5.0, "e": "1e", "f": 16, "g": 1000, "h": "e5", "i": "3e-4", "j": 2.5,
    }  # fmt: skip
    mission = parse_mission_text(MISSION.format(radius=", radius: 1e-1", more=""), "m.yaml")
    assert float(mission.params.observe_radius[0]) == pytest.approx(0.1)


def test_yaml_aliases_are_refused_where_asked():
    text = "a: &x [1, 2]\nb: *x\n"
    assert load_text(text, "YAML", "f") == {"a": [1, 2], "b": [1, 2]}
    with pytest.raises(UserError, match=r"file 'f': YAML aliases \(\*x\) are not allowed"):
        load_text(text, "YAML", "file 'f'", aliases=False)
