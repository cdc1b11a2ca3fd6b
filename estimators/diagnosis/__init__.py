"""Discrepancy diagnosis: locate a mismatch between a simulation and a recording, name the physics
left out from the effect library (:mod:`rollingstar.sensors.effects`), model it and show the fit improve.

Modules, one job each: :mod:`.observations` (observations and the simulation model's prediction,
attitude/rate nuisance), :mod:`.residuals` (locate), :mod:`.library` (candidate effects),
:mod:`.selection` (nuisance projection, screening, stepwise BIC, bootstrap, aliases),
:mod:`.refit` (nonlinear refit, joint refit with rates tied to attitudes, uncertainties,
stability), :mod:`.catchall` (unexplained systematics), :mod:`.gyro_channel` (attitude increments
against a gyro), :mod:`.resimulate` (re-simulation and residual-distribution comparison),
:mod:`.report` (HTML report and plots). Orchestrated by :mod:`rollingstar.pipelines.diagnose`.
"""
