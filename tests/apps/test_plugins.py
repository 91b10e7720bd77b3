"""The installed plugins (entry points of the project's application packages, shootlab/registry.py):
listed by name, unknown names answered with the installed ones, models, libraries and records
found through the registry."""
import pytest

from shootlab import registry


def test_registry_lists_the_installed_plugins():
    assert set(registry.names("models")) >= {"msd", "flexible", "flexible_friction", "confined"}
    assert set(registry.names("libraries")) >= {"msd", "flexible", "flexible_friction", "confined"}
    assert set(registry.names("records")) >= {"msd", "sweep", "pd", "confined"}
    assert "demo" in registry.names("commands")
    assert set(registry.names("problems")) >= {"msd", "flexible", "confined"}
    assert registry.find("models", "msd").value == "manipulators.msd:model"
    assert callable(registry.load("records", "msd"))


def test_unknown_name_lists_the_installed_ones():
    with pytest.raises(ValueError, match=r"unknown model 'warp_drive': installed models are .*msd"):
        registry.load("models", "warp_drive")
    with pytest.raises(ValueError, match=r"unknown library 'x': installed libraries are .*confined"):
        registry.load("libraries", "x")
    with pytest.raises(ValueError, match="unknown kind of plugin"):
        registry.names("gadgets")


def test_models_and_libraries_resolve_through_the_registry():
    from shootlab.diagnosis import library_for
    from shootlab.estimation.lookup import resolve_model
    model = resolve_model("msd")
    assert model.name == "msd"
    assert library_for(model).name != "generic"
    with pytest.raises(ValueError, match="installed models are"):
        resolve_model("warp_drive")


def test_simulate_record_through_the_registry(tmp_path):
    from shootlab.cli import main
    from shootlab.estimation.data import read_table
    assert main(["simulate", "msd", "--duration", "1", "--out", str(tmp_path / "m.csv")]) == 0
    data = read_table(tmp_path / "m.csv")
    assert list(data.channels) == ["u", "s"] and data.t.size == 101
