"""Discrepancy diagnosis: locate a mismatch between a simulation and a recording, name the physics
left out from the effect library (:mod:`rollingstar.sensors.effects`), model it and show the fit improve.

The algorithm, as four steps with typed results, chained by :func:`.algorithm.diagnose`:
:mod:`.locating` (held-out split, outlier rejection, where the model as given misses),
:mod:`.naming` (stepwise selection, nonlinear refinement, bootstrap and aliases),
:mod:`.modelling` (joint refit of the named effects, stability, what is left, the updated scenario),
:mod:`.verifying` (training and held-out fit before/after, re-simulation, the claims and the verdict);
:mod:`.inputs` holds the options and the simulation model a scenario builds.

The maths they use, one job per module: :mod:`.observations` (observations and the simulation
model's prediction, attitude/rate nuisance), :mod:`.residuals` (residual structure),
:mod:`.library` (candidate effects), :mod:`.signatures` (the linear problem: whitened residuals and
candidate signatures, attitude projected out), :mod:`.selection` (screening, stepwise BIC,
bootstrap, aliases), :mod:`.refit` (nonlinear refit, joint refit with rates tied to attitudes,
uncertainties, stability), :mod:`.catchall` (unexplained systematics), :mod:`.gyro_channel`
(attitude increments against a gyro), :mod:`.resimulate` (re-simulation and residual-distribution
comparison), :mod:`.report` (HTML report and plots).

The command :mod:`rollingstar.pipelines.diagnose` runs the pipeline on a recording, builds the
observations and writes the report.
"""
