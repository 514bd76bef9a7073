"""DEM ingest against the facts of the real files in ../shared/data (MANIFEST.md)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from appliance.cli.main import main
from appliance.errors import DemError
from appliance.terrain.dem import load_dem
from tests.conftest import data_file

# file, body, shape, elevation range (m), nodata cells, CRS
CASES = [
    ("dem_usgs_ascii/SainteHelens.dem", "earth", (468, 327), (682.0, 2543.0), 4151, "EPSG:26710"),
    ("dem_usgs_ascii/sanfranciscos.dem", "earth", (466, 371), (0.0, 1314 * 0.3048), None, "EPSG:26710"),
    ("dem_usgs_ascii/San_Fran_North.dem", "earth", (466, 370), (0.0, 343.0), None, "EPSG:26710"),
    ("dem_srtm_hgt/N43E006.hgt", "earth", (1201, 1201), (-12.0, 1923.0), 0, "EPSG:4326"),
    ("dem_srtm_hgt/N43E007.hgt", "earth", (1201, 1201), (-16.0, 2060.0), 4, "EPSG:4326"),
    ("dem_srtm_hgt/N44W072.hgt", "earth", (1201, 1201), (115.0, 1908.0), 0, "EPSG:4326"),
    ("dem_geotiff/N43E006_pyhgtmap.tiff", "earth", (1201, 1201), (-12.0, 1923.0), 0, "EPSG:4326"),
    ("dem_geotiff/msh00_MountStHelens_2000_webmerc.tif", "earth", (446, 307), (1361.8, 2538.1), 3154, "EPSG:3857"),
    ("dem_geotiff/gmted2010_clips/everest.tiff", "earth", (48, 48), (4983.0, 8718.0), 0, "EPSG:4326"),
    ("dem_geotiff/gmted2010_clips/matterhorn.tiff", "earth", (19, 24), (2046.0, 3595.0), 0, "EPSG:4326"),
    ("dem_geotiff/gmted2010_clips/denali.tiff", "earth", (96, 240), (1274.0, 6085.0), 0, "EPSG:4326"),
    ("dem_other/jacksboro_fault_dem.npz", "earth", (344, 403), (236.0, 1076.0), 0, "EPSG:4326"),
    ("dem_other/msh00_83_MountStHelens_2000.e00", "earth", (442, 303), (1361.8, 2538.1), 0, "EPSG:26910"),
    ("dem_planetary/LDEM_4.LBL", "moon", (720, 1440), (-8878.5, 10504.0), 0, None),
    ("dem_planetary/LDEM_4.IMG", "moon", (720, 1440), (-8878.5, 10504.0), 0, None),
]


@pytest.mark.parametrize("rel,body,shape,zrange,nodata,crs", CASES, ids=[c[0] for c in CASES])
def test_real_dems_read_with_their_facts(rel, body, shape, zrange, nodata, crs):
    dem = load_dem(data_file(rel))
    info = dem.info()
    assert info["body"] == body
    assert tuple(info["shape"]) == shape
    assert info["elevation_min_m"] == pytest.approx(zrange[0], abs=0.2)
    assert info["elevation_max_m"] == pytest.approx(zrange[1], abs=0.2)
    if nodata is not None:
        assert info["nodata_cells"] == nodata
    if crs is not None:
        assert info["crs"] == crs


def test_srtm_void_is_missing_not_zero():
    dem = load_dem(data_file("dem_srtm_hgt/N43E007.hgt"))
    raw = np.fromfile(data_file("dem_srtm_hgt/N43E007.hgt"), ">i2").reshape(1201, 1201)
    voids = raw == -32768
    assert voids.sum() == 4
    assert np.isnan(dem.elevation_m[voids]).all()
    assert np.array_equal(dem.elevation_m[~voids], raw[~voids].astype(float))


def test_hgt_and_geotiff_of_the_same_tile_agree():
    a = load_dem(data_file("dem_srtm_hgt/N43E006.hgt"))
    b = load_dem(data_file("dem_geotiff/N43E006_pyhgtmap.tiff"))
    assert np.array_equal(a.elevation_m, b.elevation_m)
    assert a.transform.almost_equals(b.transform)


def test_mount_washington_is_the_highest_point_of_n44w072():
    dem = load_dem(data_file("dem_srtm_hgt/N44W072.hgt"))
    r, c = np.unravel_index(np.nanargmax(dem.elevation_m), dem.shape)
    assert (r, c) == (875, 836)
    lon, lat = dem.xy_to_lonlat(*dem.pixel_to_xy(c, r))
    assert lat == pytest.approx(44.271, abs=0.001)
    assert lon == pytest.approx(-71.303, abs=0.001)


def test_usgs_feet_are_converted_to_metres():
    dem = load_dem(data_file("dem_usgs_ascii/sanfranciscos.dem"))
    assert dem.metadata["units"] == "ft"
    # 1314 ft is the quadrangle's highest point
    assert np.nanmax(dem.elevation_m) == pytest.approx(1314 * 0.3048, abs=0.5)


def test_lola_apollo_15_height_above_the_sphere():
    dem = load_dem(data_file("dem_planetary/LDEM_4.IMG"))
    assert dem.body.radius_m == 1_737_400.0
    x, y = dem.lonlat_to_xy(3.6285, 26.1323)
    col, row = dem.xy_to_pixel(x, y)
    assert dem.elevation_m[int(round(float(row))), int(round(float(col)))] == pytest.approx(-1924.5, abs=0.6)


def test_jacksboro_swapped_y_labels_put_north_up():
    dem = load_dem("jacksboro")
    west, south, east, north = dem.bounds_lonlat()
    assert (west, south, east, north) == pytest.approx((-84.41375, 36.44625, -84.07792, 36.73292), abs=1e-4)
    assert dem.transform.e < 0


def test_dem_info_json_cli(capsys):
    path = data_file("dem_srtm_hgt/N44W072.hgt")
    assert main(["dem", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert set(info) >= {"crs", "body", "shape", "resolution_m", "bounds_lonlat", "elevation_min_m",
                         "elevation_max_m", "nodata_cells"}
    assert info["resolution_m"][1] == pytest.approx(92.6, abs=0.2)  # 3 arc-seconds of latitude
    assert info["bounds_lonlat"] == pytest.approx([-72.0004167, 43.9995833, -70.9995833, 45.0004167], abs=1e-6)


@pytest.mark.parametrize("content", [b"", b"not a dem at all\n" * 10, b"\x00" * 4096])
def test_corrupt_dem_is_one_line_error(tmp_path, content):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(content)
    with pytest.raises(DemError, match="bad.tif"):
        load_dem(bad)
    proc = subprocess.run([sys.executable, "-m", "appliance.cli.main", "dem", "info", str(bad)],
                          capture_output=True, text=True)
    assert proc.returncode != 0
    assert proc.stderr.count("\n") == 1 and "bad.tif" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_all_nodata_and_missing_crs_are_refused(tmp_path):
    import rasterio
    from rasterio.transform import from_origin

    path = tmp_path / "empty.tif"
    with rasterio.open(path, "w", driver="GTiff", width=4, height=4, count=1, dtype="float32",
                       crs="EPSG:32632", transform=from_origin(0, 40, 10, 10), nodata=-9999) as ds:
        ds.write(np.full((1, 4, 4), -9999, np.float32))
    with pytest.raises(DemError, match="nodata"):
        load_dem(path)
    nocrs = tmp_path / "nocrs.tif"
    with rasterio.open(nocrs, "w", driver="GTiff", width=4, height=4, count=1, dtype="float32",
                       transform=from_origin(0, 40, 10, 10)) as ds:
        ds.write(np.ones((1, 4, 4), np.float32))
    with pytest.raises(DemError, match="no CRS"):
        load_dem(nocrs)
    assert load_dem(nocrs, crs="EPSG:32632").crs.to_epsg() == 32632


def test_latitude_beyond_the_pole_is_refused(tmp_path, capsys):
    import rasterio
    from rasterio.transform import from_origin

    path = tmp_path / "polar.tif"
    with rasterio.open(path, "w", driver="GTiff", width=8, height=8, count=1, dtype="float32",
                       crs="EPSG:4326", transform=from_origin(10.0, 95.0, 0.5, 0.5)) as ds:
        ds.write(np.ones((1, 8, 8), np.float32))
    with pytest.raises(DemError, match=r"latitude 94\.75 deg, beyond the pole"):
        load_dem(path)
    assert main(["dem", "info", str(path), "--json"]) == 1
    err = capsys.readouterr()
    assert err.out == "" and err.err.count("\n") == 1 and "beyond the pole" in err.err


def test_truncated_npz_is_a_dem_error(tmp_path):
    src = data_file("dem_other/jacksboro_fault_dem.npz").read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(src[: len(src) // 2])
    with pytest.raises(DemError) as err:
        load_dem(cut)
    assert str(err.value) == (f"{cut}: not a readable .npz grid (File is not a zip file): the file is damaged or "
                              "truncated")


def test_npz_with_a_damaged_compressed_member_is_a_dem_error(tmp_path):
    import zipfile

    path = tmp_path / "damaged.npz"
    np.savez_compressed(path, elevation=np.arange(400.0).reshape(20, 20), dx=1.0, dy=1.0, xmin=0.0, xmax=20.0,
                        ymin=0.0, ymax=20.0)
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("elevation.npy")
    data = bytearray(path.read_bytes())
    name_len, extra_len = int.from_bytes(data[info.header_offset + 26: info.header_offset + 28], "little"), \
        int.from_bytes(data[info.header_offset + 28: info.header_offset + 30], "little")
    start = info.header_offset + 30 + name_len + extra_len
    data[start: start + 8] = b"\xff" * 8  # a deflate block of the reserved type
    path.write_bytes(bytes(data))
    with pytest.raises(DemError, match=r"damaged\.npz: not a readable \.npz grid \(Error -3 while decompressing"):
        load_dem(path)


def test_truncated_pds_image_names_its_size(tmp_path):
    lbl = data_file("dem_planetary/LDEM_4.LBL")
    img = data_file("dem_planetary/LDEM_4.IMG")
    (tmp_path / "LDEM_4.LBL").write_bytes(lbl.read_bytes())
    (tmp_path / "LDEM_4.IMG").write_bytes(img.read_bytes()[:300_000])
    with pytest.raises(DemError) as err:
        load_dem(tmp_path / "LDEM_4.IMG")
    assert str(err.value) == (f"{tmp_path / 'LDEM_4.IMG'}: truncated: 300000 bytes, but its 1440x720 samples need "
                              "at least 2073600")


def test_srtm_tile_under_another_name_is_recognised_by_its_size(tmp_path):
    src = data_file("dem_srtm_hgt/N44W072.hgt")
    ref = load_dem(src)
    copy = tmp_path / "backup-n44w072.dat"
    copy.write_bytes(src.read_bytes())
    dem = load_dem(copy)
    assert dem.metadata["driver"] == "SRTMHGT" and dem.crs.to_epsg() == 4326
    np.testing.assert_array_equal(dem.elevation_m, ref.elevation_m)
    assert tuple(dem.transform)[:6] == pytest.approx(tuple(ref.transform)[:6], abs=1e-12)
    anonymous = tmp_path / "tile.bin"
    anonymous.write_bytes(src.read_bytes())
    with pytest.raises(DemError, match=r"size of a 3 arc-second SRTM tile \(1201x1201 int16\).*e\.g\. N44W072\.hgt"):
        load_dem(anonymous)
    odd = tmp_path / "N44W072-short.dat"
    odd.write_bytes(src.read_bytes()[:-2])
    with pytest.raises(DemError, match="not a readable DEM"):
        load_dem(odd)


def test_damaged_geotiffs_say_one_line_with_nothing_from_the_libraries(tmp_path):
    """What GDAL and libtiff print about a damaged file, and rasterio's warning about a missing
    transform, stay out of the terminal: the command's own line is all a user sees."""
    import rasterio

    src = data_file("dem_geotiff/gmted2010_clips/matterhorn.tiff").read_bytes()
    (tmp_path / "cut.tiff").write_bytes(src[: int(len(src) * 0.3)])
    with rasterio.open(tmp_path / "nogeo.tif", "w", driver="GTiff", width=8, height=8, count=1,
                       dtype="float32") as ds:
        ds.write(np.ones((1, 8, 8), np.float32))
    for name, words in (("cut.tiff", "not a readable DEM"), ("nogeo.tif", "carries no CRS")):
        out = subprocess.run([sys.executable, "-m", "appliance.cli.main", "dem", "info", name], cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 1 and out.stdout == ""
        assert out.stderr.count("\n") == 1 and words in out.stderr, out.stderr


def _small_npz(path):
    np.savez(path, elevation=np.arange(400.0).reshape(20, 20), dx=0.001, dy=0.001, xmin=7.0, xmax=7.02,
             ymin=46.0, ymax=46.02)
    return bytearray(path.read_bytes())


def test_npz_whose_zip_names_a_method_zipfile_does_not_read_is_a_dem_error(tmp_path):
    """A compression method zipfile does not know (NotImplementedError in zipfile), found by the input fuzzer."""
    path = tmp_path / "method.npz"
    data = _small_npz(path)
    for sig in (b"PK\x03\x04", b"PK\x01\x02"):  # every local and central header: method 99
        at = data.find(sig)
        while at >= 0:
            field = at + (8 if sig == b"PK\x03\x04" else 10)
            data[field:field + 2] = (99).to_bytes(2, "little")
            at = data.find(sig, at + 4)
    path.write_bytes(bytes(data))
    with pytest.raises(DemError) as err:
        load_dem(path)
    assert str(err.value) == (f"{path}: not a readable .npz grid (That compression method is not supported): the file "
                              "is damaged or truncated")


def test_npz_whose_npy_header_is_not_a_literal_is_a_dem_error(tmp_path):
    """An .npy header whose bracket never closes (TokenError in numpy's header parser), found by the input
    fuzzer; the zip itself is sound (its CRCs hold)."""
    import struct
    import zipfile

    path = tmp_path / "header.npz"
    _small_npz(path)
    header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (20, 20 ,".ljust(117) + b"\n"
    with zipfile.ZipFile(path, "a") as zf:
        members = {n: zf.read(n) for n in zf.namelist() if n != "elevation.npy"}
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("elevation.npy", b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + bytes(3200))
        for name, data in members.items():
            zf.writestr(name, data)
    with pytest.raises(DemError, match=r"header\.npz: not a readable \.npz grid \(.*\): the file is damaged"):
        load_dem(path)


def test_npz_whose_member_says_it_is_encrypted_is_a_dem_error(tmp_path):
    """A member flagged encrypted (RuntimeError in zipfile: a password is required), found by the input fuzzer."""
    path = tmp_path / "locked.npz"
    data = _small_npz(path)
    for sig, flags in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):  # every local and central header: bit 0 set
        at = data.find(sig)
        while at >= 0:
            data[at + flags] |= 1
            at = data.find(sig, at + 4)
    path.write_bytes(bytes(data))
    with pytest.raises(DemError) as err:
        load_dem(path)
    assert str(err.value).startswith(f"{path}: not a readable .npz grid (File '")
    assert "is encrypted, password required for extraction): the file is damaged or truncated" in str(err.value)
