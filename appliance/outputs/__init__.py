"""What an estimate becomes: log records, files (GeoTIFF, GeoJSON, PNG), pictures and the HTML report.

Inside, each module imports only those before it: ``features`` (the region and points every output
shows) < ``picture`` < ``files`` and ``records`` < ``report``, which builds its pages with ``html``.
"""
