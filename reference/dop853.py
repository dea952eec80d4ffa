"""The coefficients of Dormand and Prince's eighth-order Runge-Kutta formula (DOP853).

The 12-stage formula of E. Hairer, S. P. Norsett and G. Wanner, *Solving Ordinary
Differential Equations I: Nonstiff Problems*, 2nd ed., Springer 1993, section II.10, as
their Fortran code ``dop853.f`` (http://www.unige.ch/~hairer/software.html) states it and
SciPy ships it (``scipy/integrate/_ivp/dop853_coefficients.py``, BSD licence; these are its
``A[:12, :12]`` and ``B``, each written as the shortest decimal that reads back to the same
double). Kept here so that the first reference solve need not import ``scipy.integrate``
(about 1 s, issue #34); tests/test_units_reference.py checks them against SciPy's, bit for
bit.
"""

from __future__ import annotations

__all__ = ["A", "B", "N_STAGES"]

N_STAGES = 12
"""The stages of the eighth-order formula (the dense output's further stages are not used)."""

#: The Runge-Kutta matrix, row ``i`` holding ``a_ij`` for ``j < i`` (explicit).
A = (
    (),
    (0.05260015195876773,),
    (0.0197250569845379, 0.0591751709536137),
    (0.02958758547680685, 0.0, 0.08876275643042054),
    (0.2413651341592667, 0.0, -0.8845494793282861, 0.924834003261792),
    (0.037037037037037035, 0.0, 0.0, 0.17082860872947386, 0.12546768756682242),
    (0.037109375, 0.0, 0.0, 0.17025221101954405, 0.06021653898045596, -0.017578125),
    (
        0.03709200011850479,
        0.0,
        0.0,
        0.17038392571223998,
        0.10726203044637328,
        -0.015319437748624402,
        0.008273789163814023,
    ),
    (
        0.6241109587160757,
        0.0,
        0.0,
        -3.3608926294469414,
        -0.868219346841726,
        27.59209969944671,
        20.154067550477894,
        -43.48988418106996,
    ),
    (
        0.47766253643826434,
        0.0,
        0.0,
        -2.4881146199716677,
        -0.590290826836843,
        21.230051448181193,
        15.279233632882423,
        -33.28821096898486,
        -0.020331201708508627,
    ),
    (
        -0.9371424300859873,
        0.0,
        0.0,
        5.186372428844064,
        1.0914373489967295,
        -8.149787010746927,
        -18.52006565999696,
        22.739487099350505,
        2.4936055526796523,
        -3.0467644718982196,
    ),
    (
        2.273310147516538,
        0.0,
        0.0,
        -10.53449546673725,
        -2.0008720582248625,
        -17.9589318631188,
        27.94888452941996,
        -2.8589982771350235,
        -8.87285693353063,
        12.360567175794303,
        0.6433927460157636,
    ),
)
#: The weights of the eighth-order solution.
B = (
    0.054293734116568765,
    0.0,
    0.0,
    0.0,
    0.0,
    4.450312892752409,
    1.8915178993145003,
    -5.801203960010585,
    0.3111643669578199,
    -0.1521609496625161,
    0.20136540080403034,
    0.04471061572777259,
)
