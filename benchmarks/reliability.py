"""Writes docs/reliability.md: each fault and hostile-input case tried, what the code does now, and
the test that pins it, with the outcome of that test in this run and the counts of cases, of
property-based tests and the examples they ran, and of faults injected.

    python benchmarks/reliability.py              # runs every pinning test, then writes the table
    python benchmarks/reliability.py --list       # only lists the cases and their tests

The tests run in this process (pytest), so the counts of examples and faults are those of this
run (``tests/faults/tally.py``). A case whose test is not in the checkout is listed as not pinned.
Exit code 0 when every pinning test passed, 1 otherwise (the table is written either way).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

CLI = "tests/blender/test_bake_cli_faults.py"
FILES = "tests/core/test_texture_files.py"
PROPS = "tests/properties"

# (issue 21 item, case tried, behaviour, pinning test as path::function, or None while it is not pinned)
CASES: list[tuple[str, str, str, str | None]] = [
    (
        "1",
        "`python bake/bake.py --blend scene.blend` with the plain `bpy` module",
        "the checkout's add-on is registered, the stack read; texels equal the `tiny` encoder's latent",
        f"{CLI}::test_a_blend_bakes_with_the_plain_bpy_module",
    ),
    (
        "1",
        "`blender -b --python bake/bake.py -- --blend ...` with the extension enabled",
        "the enabled extension's properties and reader are used; the checkout is not registered again",
        f"{CLI}::test_a_blend_bakes_inside_blender_with_the_extension_enabled",
    ),
    (
        "1",
        "`--material` naming a material without a stack",
        "exit 2, 'has no layer stack'",
        f"{CLI}::test_a_blend_bakes_with_the_plain_bpy_module",
    ),
    (
        "1",
        "`--blend` naming a file that is not a .blend",
        "exit 2, 'cannot open it as a .blend file'",
        f"{CLI}::test_a_file_that_is_not_a_blend_is_bad_input",
    ),
    (
        "2",
        "4 `--shard` processes on one folder, all assembling at the same moment (barrier), and unsynchronised",
        "all exit 0; the texture equals the one-process bake bit for bit; only the texture and sidecar remain",
        f"{CLI}::test_concurrent_shards_on_one_folder_equal_the_single_bake_bit_for_bit",
    ),
    (
        "2",
        "a shard finds the bands gone because another shard published and removed them",
        "it checks the published texture is of its inputs and exits 0",
        f"{CLI}::test_a_shard_that_finds_the_bands_gone_after_another_published_succeeds",
    ),
    (
        "2",
        "shards run one after another, then the bake rerun",
        "union equals the single bake; rerun skips",
        "tests/blender/test_bake_cli.py::test_union_of_shards_equals_the_single_bake_and_resumes",
    ),
    (
        "5",
        "`--name` and material names `/../../x`, `..`, `a/b` vs `a_b`, `CON`, 300 characters, control characters",
        "a safe file name inside `--out` (changed names get a hash suffix, so distinct names stay distinct); the "
        "sidecar keeps the real name",
        f"{CLI}::test_hostile_names_write_inside_out_and_stay_distinct",
    ),
    (
        "5",
        "a hostile material name inside a .blend",
        "written inside `--out` under its safe name",
        f"{CLI}::test_a_blend_bakes_with_the_plain_bpy_module",
    ),
    (
        "5",
        "two materials whose names differ only in case",
        "exit 2 naming both (one file on case-blind disks)",
        f"{CLI}::test_names_equal_but_for_case_are_refused",
    ),
    (
        "6",
        "latent EXR with NaN, +Inf or -Inf texels",
        "`LatentTextureError` at read naming level, texel, channel",
        f"{FILES}::test_a_non_finite_texture_fails_at_read_naming_level_texel_and_channel",
    ),
    (
        "6",
        "latent EXR filled with NaN",
        "`LatentTextureError` (a `ValueError`) at read",
        f"{FILES}::test_a_nan_filled_texture_is_refused",
    ),
    (
        "6",
        "a baked texture damaged on disk (NaN texels, cut in half), then rendered",
        "the material renders its constant stack with a warning naming the problem",
        "tests/blender/test_texture_fallback.py::test_a_damaged_baked_texture_falls_back_to_the_constant_stack",
    ),
    (
        "6",
        "latent EXR whose mip chain stops before 1x1",
        "`LatentTextureError` at read",
        f"{FILES}::test_a_mip_chain_that_stops_early_is_refused",
    ),
    (
        "6",
        "latent EXR cut off at 10 %, 50 %, 90 %",
        "`LatentTextureError` naming the file",
        f"{FILES}::test_a_truncated_texture_is_refused",
    ),
    (
        "6",
        "random damage to a valid latent EXR (bit flips, zeroed runs, cut, spliced bytes)",
        "`LatentTextureError` naming the file, or a whole texture; never another exception",
        f"{PROPS}/test_exr_properties.py::test_a_damaged_latent_texture_is_a_clear_error_or_whole",
    ),
    (
        "6",
        "an EXR that is not a latent texture",
        "`ValueError` 'is not a latent texture'",
        "tests/core/test_textures.py::test_reading_a_non_latent_exr_is_a_clear_error",
    ),
    (
        "6",
        "texels beyond the half-float range written to an EXR",
        "`ValueError` before anything is written",
        f"{FILES}::test_values_a_half_float_cannot_hold_are_refused_at_write",
    ),
    (
        "7",
        "`--mask` with 2.0, -0.5, NaN or Inf in it",
        "exit 2 naming the file, the value, its texel and [0, 1]; nothing baked",
        f"{CLI}::test_a_mask_outside_0_1_is_bad_input_naming_file_value_and_range",
    ),
    (
        "7",
        "a kept band that is NaN, the wrong shape or unreadable (by the shard that owns it, or at assembly)",
        "never reused: baked again; the texture equals the clean bake bit for bit",
        f"{CLI}::test_an_invalid_kept_band_is_baked_again_never_reused",
    ),
    (
        "7",
        "bands of earlier inputs in the output folder",
        "not reused (keyed by every input) and removed on publish",
        f"{CLI}::test_bands_of_other_inputs_are_not_reused_and_are_cleaned",
    ),
    (
        "7",
        "bands and a finished texture baked with an earlier decoder file of the same size",
        "not reused: the key holds the decoder's digest; the texture equals a clean bake with the new decoder",
        f"{CLI}::test_bands_and_textures_of_another_decoder_file_are_not_reused",
    ),
    (
        "9",
        "`write_exr` to a folder",
        "`IsADirectoryError` and nothing written beside it",
        f"{CLI}::test_a_texture_written_to_a_folder_name_is_an_error_and_leaves_nothing",
    ),
    (
        "9",
        "a texture write interrupted part-way",
        "the previous file intact, no temporary file",
        f"{CLI}::test_a_failed_texture_write_leaves_the_old_file_and_no_temporary",
    ),
    (
        "9",
        "publishing (temporary name, flush, atomic rename) failing",
        "temporary file removed; names unique",
        f"{FILES}::test_publishing_removes_its_temporary_file_on_failure_and_renames_on_success",
    ),
    (
        "9",
        "SIGTERM and SIGINT (Ctrl-C) during a bake",
        "exit 143 / 130 with one line, no traceback, no temporary file; finished bands kept; the rerun resumes",
        f"{CLI}::test_sigterm_and_ctrl_c_exit_with_their_codes_one_line_and_no_temporary_files",
    ),
    (
        "9",
        "KeyboardInterrupt inside the command (in-process)",
        "exit 130, one line, signal handlers restored",
        f"{CLI}::test_keyboard_interrupt_in_process_is_exit_130_without_a_traceback",
    ),
    (
        "9",
        "temporary files of a killed writer; of a live one; of another machine",
        "the killed one's removed by the next run; the others left alone",
        f"{CLI}::test_temporary_files_of_a_killed_writer_are_removed_by_the_next_run_and_live_ones_kept",
    ),
    (
        "9",
        "bakes killed with SIGKILL and SIGTERM at random moments (bands, assembly, renames, clean-up, any time)",
        "no half-written file under a finished name; the rerun is bit-identical to an uninterrupted bake and "
        "leaves only the texture and sidecar",
        "tests/faults/test_bake_kill.py::test_a_bake_killed_at_random_moments_reruns_to_the_uninterrupted_texture",
    ),
    (
        "CLI",
        "argument errors (missing value, bad number, unknown option, options of the other source)",
        "exit 2 with one line `error: ...`",
        f"{CLI}::test_argument_errors_are_one_line",
    ),
    (
        "CLI",
        "random argument lists to `bake/bake.py`",
        "exit 0, 1 or 2; an error is one line; no traceback; nothing written outside `--out`",
        f"{PROPS}/test_cli_properties.py::test_bake_command_exits_0_1_or_2_with_one_line_and_writes_only_into_out",
    ),
    (
        "CLI",
        "random argument lists to `bake/demo.py`",
        "exit 0, 1 or 2; an error is one line; no traceback",
        f"{PROPS}/test_cli_properties.py::test_demo_command_exits_0_1_or_2_with_one_line",
    ),
    (
        "10",
        "`Camera.look_at` with a 0 x 0 film, a NaN eye, fov 0; a NaN point-light position; `reference_walks=0`",
        "`ValueError` naming the value",
        "tests/core/test_render.py::test_bad_settings_and_inputs_say_what_is_wrong",
    ),
    (
        "stack",
        "any valid stack (every base, 0-2 coatings, ends of every range, int / float32 values)",
        "reference albedo finite, >= 0, <= 1 within 5 standard errors; f finite and >= 0",
        f"{PROPS}/test_stack_properties.py::"
        "test_any_valid_stack_has_a_finite_non_negative_reference_with_albedo_at_most_one",
    ),
    (
        "10",
        "any invalid layer value: out of range, NaN, Inf, strings ('0.5', '111'), bools, None, complex, "
        "wrong channel counts",
        "`ValueError` naming the field",
        f"{PROPS}/test_stack_properties.py::test_any_invalid_value_is_a_value_error_naming_the_field",
    ),
    (
        "stack",
        "bases, coatings and other values in any order as a stack",
        "accepted only as a base under coatings",
        f"{PROPS}/test_stack_properties.py::test_stacks_accept_a_base_under_coatings_and_nothing_else",
    ),
    (
        "10",
        "decoder with any direction shape and dtype (complex, bool, int, float16), NaN, N = 0",
        "finite, >= 0, (N, 3); or `ValueError`",
        f"{PROPS}/test_runtime_properties.py::test_decoder_gives_finite_non_negative_values_or_a_clear_error",
    ),
    (
        "10",
        "batched encoders and sampling proxy with N = 0 .. 20 stacks of 0-2 coatings",
        "finite latents (N, 3, 32) and proxies; N = 0 gives empty arrays",
        f"{PROPS}/test_runtime_properties.py::test_batched_encoders_and_proxy_give_finite_results_for_any_batch",
    ),
    (
        "10",
        "sampling proxy of any latent array",
        "finite, sigma > 0; or `ValueError` naming z",
        f"{PROPS}/test_runtime_properties.py::test_proxy_of_any_latent_array_is_finite_or_a_clear_error",
    ),
    (
        "3",
        "a texture baked by `bake_stack` rendered (it used the default decoder size, whatever it was baked for)",
        "the texture records its size and decoder digest and is decoded with them",
        "tests/core/test_render_materials.py::test_a_baked_texture_is_decoded_with_the_size_it_was_baked_for",
    ),
    (
        "3",
        "a texture recording no size or an unknown one; an unknown `model` value",
        "`ValueError` (a bug, not a fallback)",
        "tests/core/test_render_materials.py::test_make_raises_on_textures_it_cannot_place_and_on_unknown_sizes",
    ),
    (
        "3",
        "a texture baked with another decoder file; damaged models at render time",
        "falls back with `NeuralFallbackWarning` naming the reason",
        "tests/core/test_render_materials.py::test_make_falls_back_with_a_reason_for_stale_textures_and_damaged_models",
    ),
    (
        "3",
        "a bake with the default model `auto`",
        "resolved to the default size, which the texture records",
        "tests/core/test_bake.py::test_the_default_auto_bake_uses_the_default_size_and_records_it",
    ),
    (
        "6",
        "a corrupt `.onnx` file whose card matches it",
        "`ModelFileError` naming the file",
        "tests/core/test_model_cards.py::test_a_corrupt_onnx_file_matching_its_card_is_a_typed_error",
    ),
    (
        "6",
        "a Git LFS pointer in place of an `.onnx`",
        "`ModelFileError` saying it is an LFS pointer",
        "tests/core/test_model_cards.py::test_a_git_lfs_pointer_is_named",
    ),
    (
        "8",
        "the paper decoder renamed to tiny",
        "refused: the file's digest is not its card's",
        "tests/core/test_model_cards.py::test_a_paper_decoder_renamed_to_tiny_is_refused",
    ),
    (
        "8",
        "a changed decoder or encoder under an unchanged card of the network trained with it",
        "refused, naming the card that recorded the other digest",
        "tests/core/test_model_cards.py::test_a_changed_decoder_is_caught_by_the_encoder_card",
    ),
    (
        "8",
        "a damaged model card",
        "`ModelFileError` naming the card",
        "tests/core/test_model_cards.py::test_a_damaged_card_names_the_card",
    ),
    (
        "8",
        "a card with width 0, -3, 2.5 or true",
        "`ModelFileError` naming the field",
        "tests/core/test_model_cards.py::test_a_card_with_a_bad_width_names_the_field",
    ),
    (
        "10",
        "`Diffuse('111')`, roughness `'0.5'` or `True`, complex values",
        "`ValueError` naming the field",
        "tests/core/test_stack.py::test_strings_bools_and_complex_numbers_are_not_parameters",
    ),
    (
        "10",
        "N = 0 through the batched encoders",
        "empty arrays, not a reshape error",
        "tests/core/test_neural_runtime.py::test_empty_batches_give_empty_arrays",
    ),
    (
        "4",
        "white base under smooth, non-absorbing coats of thickness 0 .. 100 (any g, ior up to 4, two coats)",
        "white furnace exact: albedo 1 with standard error 0; walks end by Russian roulette, none is cut",
        "tests/core/test_reference.py::test_white_furnace_is_exactly_one_at_every_valid_thickness",
    ),
    (
        "4",
        "a rough (alpha 0.3) white coat of thickness 0 .. 100",
        "albedo <= 1 within its standard error",
        "tests/core/test_reference.py::test_white_furnace_rough_coat_keeps_energy_at_most_one",
    ),
    (
        "4",
        "a walk that reaches the safety cap",
        "a `RuntimeWarning` naming `MAX_DEPTH` (never a silent cut)",
        "tests/core/test_reference.py::test_a_walk_cut_by_the_safety_cap_warns",
    ),
]


class Collector:
    """pytest plugin: the outcome of every test function, and which of them are property-based."""

    def __init__(self):
        self.outcomes: dict[str, list[str]] = {}
        self.properties: set[str] = set()
        self.collected: set[str] = set()

    @staticmethod
    def _function(nodeid: str) -> str:
        return nodeid.split("[")[0]

    def pytest_collection_modifyitems(self, items):
        for item in items:
            name = self._function(item.nodeid)
            self.collected.add(name)
            if getattr(getattr(item, "obj", None), "is_hypothesis_test", False):
                self.properties.add(name)

    def pytest_runtest_logreport(self, report):
        if report.when == "call" or report.outcome != "passed":
            self.outcomes.setdefault(self._function(report.nodeid), []).append(report.outcome)

    def result(self, test: str) -> str:
        got = self.outcomes.get(test)
        if test not in self.collected or not got:
            return "not in this checkout"
        return "passes" if all(o == "passed" for o in got) else "FAILS"


def _exists(test: str) -> bool:
    path, _, func = test.partition("::")
    file = ROOT / path
    return file.is_file() and f"def {func}(" in file.read_text()


def table(collector: Collector | None, seconds: float | None) -> str:
    from tests.faults import tally

    pinned = [c for c in CASES if c[3] is not None]
    tests = sorted({c[3] for c in pinned})
    rows = ["| item | case tried | behaviour | pinned by | result |", "|---|---|---|---|---|"]
    for item, case, behaviour, test in CASES:
        if test is None:
            where, result = "not pinned yet", "-"
        else:
            where = f"`{test.split('/')[-1]}`"
            result = collector.result(test) if collector else ("listed" if _exists(test) else "not in this checkout")
        rows.append(f"| {item} | {case} | {behaviour} | {where} | {result} |")
    properties = sorted(collector.properties) if collector else []
    faults = Counter(tally.FAULTS)
    kills = sum(n for k, n in faults.items() if k.startswith("SIG"))
    lines = [
        "# Reliability: faults and hostile input",
        "",
        "Written by `python benchmarks/reliability.py`, which runs every pinning test below and records what it",
        "tried. Each row is one case: what was tried, what the code does now, the test that pins it, and that test's",
        "outcome in the run that wrote this file. Property-based tests are seeded (`derandomize=True`) and bounded",
        "(`max_examples` per test), so every run draws its examples from the same seed (the counts below may differ",
        "by one or two between runs: examples Hypothesis discards part-way are counted too); explicit examples pin",
        "the cases first found by hand. Items are those of issue 21 (`CLI`: the command-line tools, `stack`: stack",
        "properties). Faults: each killed bake is rerun and compared with an uninterrupted one.",
        "",
        f"- cases: {len(CASES)} ({len(pinned)} pinned by {len(tests)} tests, {len(CASES) - len(pinned)} not yet)",
    ]
    if collector is not None:
        passed = sum(collector.result(t) == "passes" for t in tests)
        examples = ", ".join(f"`{t.split('::')[-1]}` {n}" for t, n in sorted(tally.EXAMPLES.items()))
        killed = ", ".join(f"{k}: {n}" for k, n in sorted(faults.items()) if k.startswith("SIG"))
        lines += [
            f"- pinning tests passing in this run: {passed} of {len(tests)}",
            f"- property-based tests: {len(properties)}; examples run: {sum(tally.EXAMPLES.values())} ({examples})",
            f"- faults injected: {sum(faults.values())}: {kills} bake processes killed ({killed}); "
            f"{sum(faults.values()) - kills} damaged latent EXRs read",
            f"- run time of the pinning tests: {seconds:.0f} s",
        ]
    return "\n".join(lines + ["", *rows, ""])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="list the cases and their tests without running them")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "reliability.md")
    args = ap.parse_args(argv)
    if args.list:
        print(table(None, None))
        return 0
    import pytest

    tests = sorted({c[3] for c in CASES if c[3] is not None})
    collector = Collector()
    t0 = time.perf_counter()
    present = [str(ROOT / t) for t in tests if _exists(t)]  # pytest stops at a test it cannot find
    pytest.main(["-q", "-p", "no:cacheprovider", "--rootdir", str(ROOT), *present], plugins=[collector])
    text = table(collector, time.perf_counter() - t0)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0 if all(collector.result(t) == "passes" for t in tests) else 1


if __name__ == "__main__":
    sys.exit(main())
