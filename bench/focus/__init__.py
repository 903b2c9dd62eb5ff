"""The accuracy and coverage benchmark of the focus plane, a, b and the priors (issues 10, 11).

``configs`` names the sweeps (renderer, camera, sweep, seed) and the data-sheet
offsets each is calibrated with; ``cache`` renders them once under
``out/bench/focus/<renderer>/<config>/`` and writes the manifests of the
data-sheet variants; ``evaluate`` compares a calibration with the renderer's
``truth.json`` and turns the comparisons into benchmark rows, including the
uncertainty coverage over seeds. ``bench/bench_focus.py`` runs it all.
"""
