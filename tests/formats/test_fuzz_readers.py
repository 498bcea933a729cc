"""A seeded fuzzing run over every input reader (tests/fuzz_inputs.py): broken files are refused
only with the project's own errors, never a traceback from deep inside a library (issue 15).
The 20,000-file run behind the issue's figure is `python tests/fuzz_inputs.py 20000 3`."""

import pytest
from fuzz_inputs import SHARED_REAL, fuzz


@pytest.mark.slow
def test_every_reader_refuses_broken_files_with_its_own_errors():
    findings = fuzz(400, seed=0)
    assert findings.escaped == []
    # 17 targets, 16 without ../shared beside the checkout (its Curiosity labels)
    expected = 17 if (SHARED_REAL / "curiosity_navcam_sol26_57").is_dir() else 16
    assert sum(findings.trials.values()) == 400 and len(findings.trials) == expected
    for reader in findings.trials:
        assert findings.refused[reader] > 0, reader  # the mutations do break files
