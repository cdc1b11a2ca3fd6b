"""The configs that ship with rollingstar: scenarios, pipelines, cameras and comparisons (YAML).

Commands accept them by name (``rollingstar simulate he2021b``); see
:func:`rollingstar.config.find_config`.
"""
