"""Scripts outside the CLI (benchmarks/) end on a HarnessError the way the CLI does."""

from __future__ import annotations

import pytest

from harness.errors import CheckpointError, exit_on_error


def test_a_harness_error_ends_the_script_with_its_message_and_exit_code(capsys):
    def main() -> None:
        raise CheckpointError("no artifact 'x' in run r; run it with a newer harness")

    with pytest.raises(SystemExit) as ended:
        exit_on_error(main)
    assert ended.value.code == CheckpointError.exit_code == 2
    assert capsys.readouterr().err == "error: no artifact 'x' in run r; run it with a newer harness\n"


def test_other_errors_keep_their_traceback():
    def main() -> None:
        raise ValueError("a bug")

    with pytest.raises(ValueError, match="a bug"):
        exit_on_error(main)
