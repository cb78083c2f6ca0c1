"""Generators of the documentation site's pages from the code.

``python -m coiltrack.tools.docsgen DIR`` writes the reference pages (every
command's options from its argparse parser, every scenario from the scenario
registry, every configuration key from :mod:`coiltrack.firmware.config`) into
``DIR``; ``make docs`` runs it before ``mkdocs build --strict``.
``coiltrack results`` (:mod:`coiltrack.tools.docsgen.results`) runs scenarios
and writes the results pages and the README's headline table from the same data.
"""
