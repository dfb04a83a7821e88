"""rigmix.rig: the parents-first order and the unique-name rule shared by readers, writers and stages."""

from rigmix.rig import topological_order, unique_names


def test_topological_order_is_parents_first_and_follows_the_keys():
    parent = [-1, 0, 0, 1, -1]
    key = [0, 5, 1, 0, 3]
    order = topological_order(range(5), parent.__getitem__, key.__getitem__)
    assert order == [0, 2, 4, 1, 3]
    assert all(order.index(parent[n]) < order.index(n) for n in order if parent[n] >= 0)


def test_topological_order_leaves_out_a_cycle():
    parent = [-1, 2, 1]
    assert topological_order(range(3), parent.__getitem__, lambda n: 0) == [0]


def test_unique_names_one_rule_several_suffixes():
    assert unique_names(["a", "a", "b", "a"]) == ["a", "a.001", "b", "a.002"]
    assert unique_names(["Mid", "Mid"], suffix=".{}") == ["Mid", "Mid.1"]
    assert unique_names(["a", "a", "a_2"], suffix="_{}", start=2) == ["a", "a_2", "a_2_2"]
    assert unique_names(["x"], suffix="_{}", start=2, taken={"x"}) == ["x_2"]
    # priority: the smaller keeps its name, whatever the list order
    assert unique_names(["neck", "neck"], priority=[1, 0]) == ["neck.001", "neck"]
