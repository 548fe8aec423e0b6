"""The benchmark cache notices a scene synthesised with other code or libraries."""
import json

from benchmarks.common import version_changes


def test_version_changes_names_what_moved(tmp_path):
    now = {"nefii": "0.1.0", "synth_source": "abc", "mitsuba": "3.9.1", "platform": "linux"}
    (tmp_path / "scene.json").write_text(json.dumps({"versions": {**now, "platform": "darwin"}}))
    assert version_changes(tmp_path, now) == ""                      # the platform alone is not a change
    (tmp_path / "scene.json").write_text(json.dumps({"versions": {**now, "mitsuba": "3.8.0"}}))
    assert version_changes(tmp_path, now) == "mitsuba 3.8.0 -> 3.9.1"
    (tmp_path / "scene.json").write_text(json.dumps({"versions": {"nefii": "0.1.0", "mitsuba": "3.9.1"}}))
    assert version_changes(tmp_path, now) == "synth_source None -> abc"


def test_version_changes_of_an_unreadable_record(tmp_path):
    (tmp_path / "scene.json").write_text("{not json")
    assert "mitsuba None -> 3.9.1" in version_changes(tmp_path, {"mitsuba": "3.9.1"})
    assert version_changes(tmp_path / "missing", {"mitsuba": "3.9.1"}) == "mitsuba None -> 3.9.1"


def test_a_results_note_is_a_paragraph_from_text_or_a_file(tmp_path):
    from benchmarks.common import note_lines

    assert note_lines("") == [] and note_lines("  \n") == []
    assert note_lines(" rows refitted at abc. ") == ["rows refitted at abc.", ""]
    (tmp_path / "note.md").write_text("How the rows were made:\ntwo at a time.\n")
    assert note_lines(f"@{tmp_path / 'note.md'}") == ["How the rows were made:\ntwo at a time.", ""]


def test_a_cached_geometry_stage_is_reused_only_at_the_same_settings():
    from benchmarks.geometry import geometry_folder

    base = geometry_folder("bowl_128", "on", "cpu", [])
    assert base == geometry_folder("bowl_128", "on", "cpu", ["threads=2"])        # threads do not change a stage
    others = {geometry_folder("bowl_128", "on", "cpu", ["steps=6000"]), geometry_folder("bowl_128", "on", "gpu", []),
              geometry_folder("bowl_128", "off", "cpu", []), geometry_folder("cup_128", "on", "cpu", [])}
    assert base not in others and len(others) == 4
    assert "steps=6000" in geometry_folder("bowl_128", "on", "cpu", ["steps=6000"]).name


def test_a_photo_run_through_the_geometry_stage_is_named_by_its_settings():
    from benchmarks.common import fit_digest
    from benchmarks.geometry import stage_digest
    from benchmarks.photo import photo_run, photo_sets

    assert photo_run("cup", "geometry", 0).name == (f"photo_cup_geometry_s0_{stage_digest('cpu', [])}_"
                                                   f"{fit_digest(photo_sets('geometry', 0))}")
    assert stage_digest("cpu", []) != stage_digest("cpu", ["steps=12000"])
    assert photo_run("cup", "mesh", 0).name == f"photo_cup_mesh_s0_{fit_digest(photo_sets('mesh', 0))}"   # no stage
    assert photo_run("cup", "mesh", 0) != photo_run("cup", "mesh", 1)


def test_a_cached_fit_is_reused_only_at_the_same_settings():
    from benchmarks.common import fit_digest
    from benchmarks.heldout import run_dir as heldout_run
    from benchmarks.quality import run_dir

    full = run_dir("bowl", "full")
    assert full == run_dir("bowl", "full", ["threads=1", "checkpoint_every_s=5"])   # neither changes a fit
    others = {run_dir("bowl", "full", ["seed=1"]), run_dir("bowl", "full", ["steps=6000"]),
              run_dir("bowl", "indirect_off"), run_dir("cup", "full")}
    assert full not in others and len(others) == 4
    assert run_dir("bowl", "indirect_off").name.startswith("bowl_indirect_off_")
    assert fit_digest(["seed=0"]) == fit_digest([]) != fit_digest(["seed=1"])    # the default seed is seed 0
    assert heldout_run("cup", 0) != heldout_run("cup", 0, ["num_samples=16"])
