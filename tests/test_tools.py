"""Tools told apart by their layouts (markerpose.tools) and `markerpose tools`."""

import pytest

from markerpose import Marker
from markerpose.cli import main
from markerpose.tools import MIN_DIFFERENCE_MM, check_tools, layout_difference, least_difference, load_tools, tool_set


def test_layout_difference_is_zero_for_one_layout_in_any_order_and_grows_with_a_moved_ring():
    a = Marker()
    assert layout_difference(a, a) < 1e-9
    assert layout_difference(a, Marker(name="other")) < 1e-9  # the name is not the layout
    moved = Marker(c2=(0.0, 46.0))
    assert 2.0 < layout_difference(a, moved) < 3.0  # 6 mm along one side, spread over three centres
    assert layout_difference(a, moved) == pytest.approx(layout_difference(moved, a), abs=1e-9)


def test_a_generated_set_is_told_apart_with_margin():
    tools = tool_set(4)
    assert [t.name for t in tools] == ["tool1", "tool2", "tool3", "tool4"]
    assert (tools[0].c1, tools[0].c2) == (Marker().c1, Marker().c2)  # the paper's layout first
    assert least_difference(tools) >= MIN_DIFFERENCE_MM
    for t in tools:
        x0, y0, x1, y1 = t.plate
        assert max(x1 - x0, y1 - y0) <= 100.0


def test_tools_that_cannot_be_told_apart_are_refused_by_file(tmp_path):
    a = Marker(name="probe").save(tmp_path / "probe.yaml")
    b = Marker(name="probe", c2=(-10.0, 55.0)).save(tmp_path / "probe2.yaml")
    with pytest.raises(ValueError, match=r"probe\.yaml and .*probe2\.yaml: two tools named 'probe'"):
        load_tools([a, b])
    c = Marker(name="pointer", c2=(0.0, 42.0)).save(tmp_path / "pointer.yaml")
    with pytest.raises(ValueError, match=r"probe\.yaml and .*pointer\.yaml: the layouts of 'probe' and 'pointer' differ by 0\.\d\d mm"):
        load_tools([a, c])
    assert [t.name for t in load_tools([a])] == ["probe"]
    with pytest.raises(ValueError, match="count must be 1 to 12"):
        tool_set(0)
    assert check_tools([]) == []


def test_cli_writes_a_set_of_tool_files_and_targets(tmp_path, capsys):
    assert main(["tools", "--count", "2", "--out", str(tmp_path / "set")]) == 0
    out = capsys.readouterr().out
    assert "least layout difference between two tools" in out
    files = sorted(p.name for p in (tmp_path / "set").iterdir())
    assert files == ["tool1.pdf", "tool1.yaml", "tool2.pdf", "tool2.yaml"]
    tools = load_tools([tmp_path / "set" / "tool1.yaml", tmp_path / "set" / "tool2.yaml"])
    assert tools == tool_set(2)
    assert (tmp_path / "set" / "tool2.pdf").read_bytes().startswith(b"%PDF")
