"""What an estimate becomes: log records, files (GeoTIFF, GeoJSON, PNG), pictures and the HTML report."""
