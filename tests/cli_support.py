"""What the command-line test modules share (test_fit_cli, test_hostile, test_hostile_6):
the milk's simulated stripe capture as a ``simulate`` config (32×24, six shifts, dark
frame, shot and read noise) and the CLI runners. Fixtures stay in each module (their
autouse environment applies to that module alone)."""

from lightfield_jax.app.cli import main

H, W = 24, 32
SIMULATE = f"""\
grid: {{width: {W}, height: {H}, n_theta: 16, refine: 1}}
medium: {{sigma_t: 0.2051, sigma_s: 0.0366, g: 0.4, phase: paper}}
illumination: {{kind: stripes, period: 6, lit: 3}}
gain: 400.0
black_level: 0.02
dark_level: 0.01
noise: {{photons: 1.0e5, read: 0.0005, seed: 3}}
"""


def run(capsys, *argv):
    """``lightfield-jax ARGV``: its exit status, standard output and error."""
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def refused(capsys, *argv, match: str) -> str:
    """The command exits 2 with one error line containing ``match``."""
    status, out, err = run(capsys, *argv)
    lines = err.splitlines()
    assert status == 2, (status, out, err)
    assert len(lines) == 1 and lines[0].startswith("lightfield-jax: error: "), err
    assert match in lines[0], lines[0]
    assert "Traceback" not in err and "Warning" not in err
    return lines[0]
