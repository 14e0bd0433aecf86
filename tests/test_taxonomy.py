import json

import numpy as np
import pytest

from occufly.errors import TaxonomyError
from occufly.taxonomy import Taxonomy, default_taxonomy


def test_default_table_matches_formats():
    tax = default_taxonomy()
    assert len(tax) == 21
    assert tax.ids.tolist() == [1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14, 16, 17, 21, 22, 33, 34, 35, 36]
    assert tax[16].name == "building" and tax[16].rgb == (255, 0, 0)
    assert tax[11].dbscan_eps == 0.3 and tax[11].dbscan_min_points == 10
    assert tax[16].dbscan_eps == 4.0 and tax[16].dbscan_min_points == 1000
    assert set(tax.group_ids("instance").tolist()) == {11, 12, 13, 16, 17, 35, 36}
    assert set(tax.group_ids("ground").tolist()) == {1, 2, 3, 4, 6, 7, 14, 33}
    assert set(tax.group_ids("other").tolist()) == {5, 8, 9, 21, 22, 34}
    # tie order: more frequent first
    order = tax.tie_order.tolist()
    assert order[:3] == [16, 6, 8] and order[-1] == 11
    lut = tax.priority_lut()
    assert lut[16] == 0 and lut[0] == -1 and lut[255] == -1
    assert tax.colour_lut()[33].tolist() == [128, 64, 128]


def test_learning_map_contiguous():
    m = default_taxonomy().learning_map()
    assert m[0] == 0 and m[255] == 255
    assert sorted(v for k, v in m.items() if k not in (0, 255)) == list(range(1, 22))


def test_roundtrip_json_and_yaml(tmp_path):
    tax = default_taxonomy()
    p = tmp_path / "t.json"
    tax.save(p)
    assert Taxonomy.load(p) == tax
    import yaml

    y = tmp_path / "t.yaml"
    y.write_text(yaml.safe_dump(tax.to_dict()))
    assert Taxonomy.load(y).tie_order.tolist() == tax.tie_order.tolist()


@pytest.mark.parametrize(
    "rows, message",
    [
        ([{"id": 1, "name": "a", "rgb": [1, 2, 3], "group": "ground"},
          {"id": 1, "name": "b", "rgb": [1, 2, 3], "group": "ground"}], "duplicate class id 1"),
        ([{"id": 0, "name": "a", "rgb": [1, 2, 3], "group": "ground"}], "reserved"),
        ([{"id": 255, "name": "a", "rgb": [1, 2, 3], "group": "ground"}], "reserved"),
        ([{"id": 3, "name": "a", "rgb": [1, 2, 3], "group": "sky"}], "unknown group 'sky'"),
        ([{"id": 3, "name": "a", "rgb": [1, 2], "group": "ground"}], "rgb must be three"),
        ([{"id": 3, "name": "a", "rgb": [1, 2, 3], "group": "instance"}], "needs dbscan_eps"),
        ([{"id": 3, "rgb": [1, 2, 3], "group": "ground"}], "missing field(s) name"),
    ],
)
def test_invalid_taxonomy_files(tmp_path, rows, message):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps({"classes": rows}))
    with pytest.raises(TaxonomyError) as e:
        Taxonomy.load(p)
    assert message in str(e.value) and str(p) in str(e.value)


def test_unparseable_file(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(TaxonomyError, match="not valid"):
        Taxonomy.load(p)


def test_custom_taxonomy_drives_luts(tmp_path):
    tax = Taxonomy.from_dict({"name": "mine", "classes": [
        {"id": 7, "name": "soil", "rgb": [1, 2, 3], "group": "ground", "freq": 1},
        {"id": 200, "name": "car", "rgb": [9, 9, 9], "group": "instance", "freq": 5,
         "dbscan_eps": 1, "dbscan_min_points": 5},
    ]})
    assert tax.tie_order.tolist() == [200, 7]
    assert np.flatnonzero(tax.valid_lut()).tolist() == [7, 200]


def test_asprs_codes_default_custom_and_invalid():
    from occufly.taxonomy import Taxonomy, default_taxonomy

    t = default_taxonomy()
    lut = t.asprs_lut()
    assert lut[0] == 1 and lut[t.by_name("building").id] == 6 and lut[t.by_name("tree").id] == 5
    assert lut[t.by_name("walkway").id] == 64  # no standard code: first user-definable one
    # a default table saved before the asprs column existed reads with the same codes
    d = t.to_dict()
    for row in d["classes"]:
        del row["asprs"]
    assert np.array_equal(Taxonomy.from_dict(d).asprs_lut(), lut)
    # a custom table: its own codes; an unknown code is refused, naming the class
    d = {"name": "mine", "classes": [{"id": 1, "name": "pavement", "rgb": [1, 2, 3],
                                      "group": "ground", "asprs": 11},
                                     {"id": 2, "name": "hedge", "rgb": [1, 2, 4], "group": "other"}]}
    c = Taxonomy.from_dict(d)
    assert c.asprs_lut()[1] == 11 and c.asprs_lut()[2] == 64
    d["classes"][0]["asprs"] = 8
    with pytest.raises(TaxonomyError, match="pavement.*asprs code 8"):
        Taxonomy.from_dict(d)
