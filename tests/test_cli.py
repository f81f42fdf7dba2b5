import subprocess
import sys

import pytest

from pallet6d.runtime import cli


def test_help_lists_every_subcommand(capsys):
    assert cli.main([]) == 0
    out = capsys.readouterr().out
    for name in cli.SUBCOMMANDS:
        assert name in out


def test_help_does_not_import_heavy_modules():
    code = ("import sys; from pallet6d.runtime import cli; cli.main([]); "
            "heavy = [m for m in ('torch', 'onnx', 'pallet6d.export', 'pallet6d.sim') if m in sys.modules]; "
            "print(heavy); sys.exit(1 if heavy else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_unknown_subcommand_is_an_error():
    with pytest.raises(SystemExit) as exc:
        cli.main(["no-such-command"])
    assert exc.value.code == 2
