"""``hitops report``: one page per run (``DIR/index.html``) that shows what a run did.

The pipeline of this tool, one module per job: :mod:`.collect` reads what the run
left in its directory into typed facts, :mod:`.steps` reads Stimela's logs,
:mod:`.provenance` gathers versions, parameters and checksums, :mod:`.images`
renders the FITS images, :mod:`.page` writes the HTML (docs/report.md).
"""

from .api import report  # noqa: F401,E402
