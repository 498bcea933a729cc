"""Orbital maps: GeoTIFF DTMs and orthoimages, maps on the local frame, and a site registered to
them (its points to the DTM, its ground from above to the orthoimage). The factor and the map
bias are the orbital kind's (kinds/orbital.py)."""
