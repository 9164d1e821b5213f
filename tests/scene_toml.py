"""Scene-file text of the bodies the scene tests put under colliders (tests/test_cli_fuzz.py,
tests/test_contact_hooks.py): one writer of each [[objects]] table, so the tests differ only in
the numbers they choose."""


def _vector(values):
    return "[" + ", ".join(repr(float(c)) for c in values) + "]"


def fem_box(lower, upper, youngs_modulus, density, cells=(1, 1, 1), poisson_ratio=0.3):
    """The keys of a km.fem box object (without its [[objects]] header)."""
    return (f'type = "box"\nlower = {_vector(lower)}\nupper = {_vector(upper)}\n'
            f'cells = [{", ".join(str(int(c)) for c in cells)}]\nyoungs_modulus = {float(youngs_modulus)!r}\n'
            f'poisson_ratio = {float(poisson_ratio)!r}\ndensity = {float(density)!r}')


def cloth(resolution, size, origin, stiffness, mass, plane="xz"):
    """The keys of a km.massspring cloth object (without its [[objects]] header)."""
    return (f'type = "cloth"\nresolution = [{", ".join(str(int(c)) for c in resolution)}]\n'
            f'size = {_vector(size)}\norigin = {_vector(origin)}\nplane = "{plane}"\n'
            f'stiffness = {float(stiffness)!r}\nmass = {float(mass)!r}')
