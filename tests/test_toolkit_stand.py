"""The stand summary (toolkit.outputs.stand) checked against figures computed by hand."""
import math

import numpy as np
import pytest

from monodbh.calib.errors import MonodbhError
from monodbh.toolkit.outputs.stand import (CLASS_WIDTH_CM, ResultsFileError, basal_area_m2,
                                           basal_area_sigma_m2, dbh_classes, read_plots,
                                           stand_summary)

HEADER = "photo,dbh_cm,dbh_sigma_cm,distance_m,scale_source,flags,error,timings_ms,estimates_cm,rope_xy,tree_id"


def _csv(path, rows, header=HEADER):
    path.write_text(header + "\n" + "".join(r + "\n" for r in rows), encoding="utf-8")
    return path


def _row(photo, dbh="", sigma="", error=""):
    return f'{photo},{dbh},{sigma},2.1,stem_base,[],{error},"{{}}","{{}}",,'


@pytest.fixture()
def three(tmp_path):
    """DBHs 10, 20, 30 cm (sigmas 1, 2, 3 cm) and one photo not measured."""
    return _csv(tmp_path / "plot_a.csv", [_row("a.jpg", 10, 1), _row("b.jpg", 20, 2), _row("c.jpg", 30, 3),
                                          _row("d.jpg", error="no rope found")])


def test_one_plot_by_hand(three):
    s = stand_summary([three], plot_area_m2=400.0)
    p = s.plots[0]
    assert p.plot.endswith("plot_a.csv") and p.photos == 4 and p.trees == 3 and p.not_measured == 1
    # mean (10 + 20 + 30) / 3 = 20
    assert p.dbh_mean_cm == pytest.approx(20.0)
    # sample std: deviations -10, 0, 10 -> sqrt((100 + 0 + 100) / 2) = 10; SE = 10 / sqrt(3) = 5.7735
    assert p.dbh_mean_se_cm == pytest.approx(5.7735, abs=1e-4)
    # QMD sqrt((100 + 400 + 900) / 3) = sqrt(466.667) = 21.602
    assert p.dbh_quadratic_mean_cm == pytest.approx(21.602, abs=1e-3)
    assert (p.dbh_min_cm, p.dbh_max_cm) == (10.0, 30.0)
    # BA = pi/4 * (0.10^2 + 0.20^2 + 0.30^2) = pi/4 * 0.14 = 0.109956 m^2
    assert p.basal_area_m2 == pytest.approx(0.109956, abs=1e-6)
    # per ha on 400 m^2: x 10000 / 400 = x 25 -> 0.109956 * 25 = 2.74889 m^2/ha; 3 * 25 = 75 stems/ha
    assert p.basal_area_m2_per_ha == pytest.approx(2.74889, abs=1e-5)
    assert p.stems_per_ha == pytest.approx(75.0)
    # sigma_BA_i = pi * d * s / 20000: pi*10/20000 = 0.0015708, pi*40/20000 = 0.0062832,
    # pi*90/20000 = 0.0141372; sqrt(sum of squares) = pi/20000 * sqrt(100 + 1600 + 8100)
    #   = 1.5708e-4 * 98.995 = 0.0155501 m^2; per ha x 25 = 0.388752
    assert p.basal_area_sigma_m2 == pytest.approx(0.0155501, abs=1e-7)
    assert p.basal_area_sigma_m2_per_ha == pytest.approx(0.388752, abs=1e-6)
    assert p.trees_without_sigma == 0
    # one plot: all plots = the plot
    assert s.all_plots.trees == 3 and s.all_plots.basal_area_m2 == pytest.approx(p.basal_area_m2)


def test_the_docstring_example_of_ten_twenty_thirty_without_area(three):
    p = stand_summary([three]).plots[0]
    assert p.stems_per_ha is None and p.basal_area_m2_per_ha is None and p.area_m2 is None
    assert p.basal_area_m2 == pytest.approx(math.pi / 4 * 0.14)


def test_two_plots_as_two_files(tmp_path, three):
    # plot b: 40 cm (sigma 2) and 50 cm (no sigma)
    b = _csv(tmp_path / "plot_b.csv", [_row("e.jpg", 40, 2), _row("f.jpg", 50)])
    s = stand_summary([three, b], plot_area_m2=400.0)
    assert [p.trees for p in s.plots] == [3, 2]
    pb = s.plots[1]
    # mean 45, QMD sqrt((1600 + 2500) / 2) = sqrt(2050) = 45.277
    assert pb.dbh_mean_cm == pytest.approx(45.0) and pb.dbh_quadratic_mean_cm == pytest.approx(45.277, abs=1e-3)
    # BA = pi/4 * (0.16 + 0.25) = pi/4 * 0.41 = 0.322013 m^2
    assert pb.basal_area_m2 == pytest.approx(0.322013, abs=1e-6)
    # only the 40 cm tree has a sigma: pi * 40 * 2 / 20000 = 0.0125664 m^2
    assert pb.basal_area_sigma_m2 == pytest.approx(0.0125664, abs=1e-7) and pb.trees_without_sigma == 1
    a = s.all_plots
    assert a.plots == 2 and a.photos == 6 and a.trees == 5 and a.not_measured == 1 and a.area_m2 == 800.0
    # pooled: mean (10+20+30+40+50)/5 = 30; QMD sqrt((100+400+900+1600+2500)/5) = sqrt(1100) = 33.166
    assert a.dbh_mean_cm == pytest.approx(30.0) and a.dbh_quadratic_mean_cm == pytest.approx(33.166, abs=1e-3)
    # SE: sample std of 10..50 = sqrt((400+100+0+100+400)/4) = sqrt(250) = 15.811; / sqrt(5) = 7.0711
    assert a.dbh_mean_se_cm == pytest.approx(7.0711, abs=1e-4)
    # BA = pi/4 * (0.14 + 0.41) = pi/4 * 0.55 = 0.431969 m^2; on 800 m^2: x 12.5 = 5.39961 m^2/ha
    assert a.basal_area_m2 == pytest.approx(0.431969, abs=1e-6)
    assert a.basal_area_m2_per_ha == pytest.approx(5.39961, abs=1e-5)
    # 5 stems on 800 m^2 = 62.5 /ha (the mean of 75 and 50)
    assert a.stems_per_ha == pytest.approx(62.5)
    # sigma: sqrt(0.0155501^2 + 0.0125664^2) = sqrt(2.41806e-4 + 1.57914e-4) = 0.0199930
    assert a.basal_area_sigma_m2 == pytest.approx(0.0199930, abs=1e-6)


def test_two_plots_by_a_plot_column(tmp_path):
    header = HEADER + ",plot"
    p = _csv(tmp_path / "all.csv", [_row("a.jpg", 10, 1) + ",P1", _row("b.jpg", 40) + ",P2",
                                    _row("c.jpg", 30, 3) + ",P1", _row("d.jpg", error="blurred") + ",P2"],
             header=header)
    s = stand_summary([p], plot_area_m2=100.0)
    assert [q.plot for q in s.plots] == ["P1", "P2"]
    p1, p2 = s.plots
    assert (p1.photos, p1.trees, p2.photos, p2.trees) == (2, 2, 2, 1)
    # P1: mean 20; BA = pi/4 * (0.01 + 0.09) = 0.0785398 m^2; on 100 m^2: x 100 = 7.85398 m^2/ha, 200 stems/ha
    assert p1.dbh_mean_cm == pytest.approx(20.0) and p1.basal_area_m2 == pytest.approx(0.0785398, abs=1e-7)
    assert p1.basal_area_m2_per_ha == pytest.approx(7.85398, abs=1e-5) and p1.stems_per_ha == pytest.approx(200)
    # P2: one tree: no standard error; BA pi/4 * 0.16 = 0.125664
    assert p2.dbh_mean_se_cm is None and p2.basal_area_m2 == pytest.approx(0.125664, abs=1e-6)
    assert s.all_plots.area_m2 == 200.0 and s.all_plots.stems_per_ha == pytest.approx(150.0)


def test_a_plot_split_over_two_files_is_one_plot(tmp_path):
    header = HEADER + ",plot"
    a = _csv(tmp_path / "day1.csv", [_row("a.jpg", 10) + ",P1"], header=header)
    b = _csv(tmp_path / "day2.csv", [_row("b.jpg", 20) + ",P1"], header=header)
    (p,) = read_plots([a, b])
    assert p.plot == "P1" and p.trees == 2 and len(p.sources) == 2


def test_classes_by_hand(tmp_path):
    # 4.9 -> 0-5; 5.0 -> 5-10 (lower bound included); 12, 14.99 -> 10-15; none in 15-20; 20 -> 20-25
    p = _csv(tmp_path / "c.csv", [_row(f"{k}.jpg", d) for k, d in enumerate((4.9, 5.0, 12, 14.99, 20))])
    s = stand_summary([p], plot_area_m2=500.0)
    got = [(c.dbh_class_cm, c.trees) for c in s.dbh_classes]
    assert got == [("0-5", 1), ("5-10", 1), ("10-15", 2), ("15-20", 0), ("20-25", 1)]
    c10 = s.dbh_classes[2]
    # pi/4 * (0.12^2 + 0.1499^2) = pi/4 * (0.0144 + 0.02247001) = 0.0289576 m^2; x 10000/500 = 0.579153
    assert c10.basal_area_m2 == pytest.approx(0.0289576, abs=1e-7)
    assert c10.basal_area_m2_per_ha == pytest.approx(0.579153, abs=1e-6) and c10.stems_per_ha == 40.0
    assert (c10.lower_cm, c10.upper_cm) == (10.0, 15.0) and CLASS_WIDTH_CM == 5.0
    # the classes add up to the stand
    assert sum(c.trees for c in s.dbh_classes) == 5
    assert sum(c.basal_area_m2 for c in s.dbh_classes) == pytest.approx(s.all_plots.basal_area_m2)
    assert dbh_classes(np.zeros(0)) == []


def test_sigma_propagation_matches_a_monte_carlo():
    d = np.array([12.0, 25.0, 41.0])
    s = np.array([0.8, 1.5, 2.5])
    rng = np.random.default_rng(0)
    draws = basal_area_m2(d + rng.normal(size=(200000, 3)) * s).sum(axis=1)
    assert basal_area_sigma_m2(d, s) == pytest.approx(np.std(draws), rel=0.01)
    # unknown sigmas add nothing
    assert basal_area_sigma_m2(d, [0.8, np.nan, np.nan]) == pytest.approx(math.pi * 12 * 0.8 / 20000)


def test_empty_csv_is_a_plot_with_no_trees(tmp_path):
    p = _csv(tmp_path / "empty.csv", [])
    s = stand_summary([p], plot_area_m2=400.0)
    (q,) = s.plots
    assert q.photos == 0 and q.trees == 0 and q.basal_area_m2 == 0.0 and q.stems_per_ha == 0.0
    assert q.dbh_mean_cm is None and q.dbh_quadratic_mean_cm is None and s.dbh_classes == []


def test_only_failed_photos(tmp_path):
    p = _csv(tmp_path / "f.csv", [_row("a.jpg", error="no rope found"), _row("b.jpg", 33, 1, error="x")])
    (q,) = stand_summary([p]).plots
    assert q.photos == 2 and q.trees == 0 and q.not_measured == 2


def test_minimal_columns_and_a_bom(tmp_path):
    p = tmp_path / "excel.csv"
    p.write_bytes("\ufeffdbh_cm\r\n10\r\n\r\n20\r\n".encode("utf-8"))
    (q,) = read_plots([p])
    assert q.trees == 2 and q.photos == 2 and np.isnan(q.dbh_sigma_cm).all()


@pytest.mark.parametrize("cell, problem", [("abc", "is not a number"), ("-3", "is negative"),
                                           ("nan", "is not finite"), ("inf", "is not finite")])
def test_bad_dbh_names_the_file_and_the_row(tmp_path, cell, problem):
    p = _csv(tmp_path / "bad.csv", [_row("a.jpg", 10), _row("b.jpg", cell)])
    with pytest.raises(ResultsFileError) as e:
        read_plots([p])
    msg = str(e.value)
    assert isinstance(e.value, MonodbhError) and "\n" not in msg
    assert msg.startswith(str(p)) and "row 3 (b.jpg)" in msg and "dbh_cm" in msg and problem in msg


def test_bad_sigma_is_refused(tmp_path):
    p = _csv(tmp_path / "bad.csv", [_row("a.jpg", 10, "-1")])
    with pytest.raises(ResultsFileError, match=r"row 2 \(a\.jpg\): dbh_sigma_cm '-1' is negative"):
        read_plots([p])


def test_missing_file_folder_and_no_dbh_column(tmp_path):
    with pytest.raises(ResultsFileError, match="nope.csv: no such file"):
        read_plots([tmp_path / "nope.csv"])
    with pytest.raises(ResultsFileError, match="is a folder"):
        read_plots([tmp_path])
    p = _csv(tmp_path / "other.csv", ["1,2"], header="a,b")
    with pytest.raises(ResultsFileError, match="other.csv: no dbh_cm column"):
        read_plots([p])
    z = tmp_path / "zero.csv"
    z.write_bytes(b"")
    with pytest.raises(ResultsFileError, match="zero.csv: no dbh_cm column"):
        read_plots([z])


def test_not_utf8_empty_plot_and_twice(tmp_path, three):
    p = tmp_path / "latin1.csv"
    p.write_bytes(b"photo,dbh_cm\nc\xe9dre.jpg,10\n")
    with pytest.raises(ResultsFileError, match="not a UTF-8"):
        read_plots([p])
    q = _csv(tmp_path / "plots.csv", [_row("a.jpg", 10) + ","], header=HEADER + ",plot")
    with pytest.raises(ResultsFileError, match=r"row 2 \(a\.jpg\): empty plot"):
        read_plots([q])
    with pytest.raises(ResultsFileError, match="given twice"):
        read_plots([three, three])


def test_bad_area_is_a_programming_error(three):
    for a in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            stand_summary([three], plot_area_m2=a)


def test_json_dict_is_plain(three):
    import json

    d = stand_summary([three], plot_area_m2=400.0).to_json_dict()
    json.dumps(d, allow_nan=False)
    assert d["plot_area_m2"] == 400.0 and d["all_plots"]["stems_per_ha"] == 75.0
    assert d["dbh_classes"][0]["dbh_class_cm"] == "10-15"
