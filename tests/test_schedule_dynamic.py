"""Navrátil's ray-weighted round decision (``schedule.dynamic``) on hand-made inputs: no
sockets, no nodes."""

from __future__ import annotations

from vastray.schedule.dynamic import RayWeightedRounds, Round

POLICY = RayWeightedRounds()


def test_a_loaded_domain_still_wanted_stays_where_it_is():
    # node 1 has domain 4 loaded and node 0 has rays for it: 4 stays on node 1, no load
    plan = POLICY.next_round({0: {"4": 7}, 1: {}}, {0: [2], 1: [4]})
    assert plan.assign == {4: 1}
    assert not plan.finished


def test_the_most_wanted_unloaded_domain_goes_to_a_node_whose_domains_are_no_longer_wanted():
    queues = {0: {"3": 10, "5": 2}, 1: {"7": 30}, 2: {"5": 1}}
    loaded = {0: [3], 1: [9], 2: []}
    # 3 stays on node 0; 7 (30 rays) then 5 (3 rays, summed over nodes) go to the nodes
    # whose resident domains nobody wants, in rank order
    assert POLICY.next_round(queues, loaded).assign == {3: 0, 7: 1, 5: 2}


def test_weights_are_summed_over_every_nodes_queue():
    # 8 has 3 + 3 = 6 rays in all, 6 has 5 on one node: 8 is the most wanted
    plan = POLICY.next_round({0: {"6": 5, "8": 3}, 1: {"8": 3}}, {0: [], 1: []})
    assert list(plan.assign.items()) == [(8, 0), (6, 1)]


def test_the_whole_resident_set_counts_not_only_the_last_domain():
    queues = {0: {"3": 10, "5": 2}, 1: {"7": 30}, 2: {"5": 1}}
    # 5 is still in node 2's cache beside 4: it stays there and no node loads it again
    assert POLICY.next_round(queues, {0: [3], 1: [9], 2: [4, 5]}).assign == {3: 0, 5: 2, 7: 1}


def test_a_domain_resident_on_two_nodes_stays_with_the_lower_rank():
    plan = POLICY.next_round({0: {}, 1: {"2": 4}, 2: {}}, {2: [2], 0: [], 1: [2]})
    assert plan.assign == {2: 1}


def test_ties_go_to_the_lower_domain_id():
    plan = POLICY.next_round({0: {"9": 4, "1": 4}, 1: {"5": 4}}, {0: [], 1: []})
    # three domains of equal weight, two free nodes: 1 and 5 go, in that order; 9 waits
    assert list(plan.assign.items()) == [(1, 0), (5, 1)]


def test_free_nodes_are_taken_in_rank_order_and_busy_ones_are_skipped():
    # node 0 keeps 3; nodes 1 and 2 are free, so 6 (most wanted) goes to 1 and 2 to 2
    plan = POLICY.next_round({2: {"3": 1, "6": 9}, 0: {"2": 5}, 1: {}},
                             {2: [], 1: [8], 0: [3]})
    assert plan.assign == {3: 0, 6: 1, 2: 2}
    assert list(plan.assign)[0] == 3  # kept domains come first: each node traces in this order


def test_a_busy_node_takes_a_domain_that_keeps_the_round_as_short():
    # node 0 keeps 3 (10 rays), node 1 keeps 7 (20): unheld 5's 4 rays go to node 0, which
    # then traces 14, under the round's busiest 20; with the paper's rule 5 waits
    queues = {0: {"3": 10, "5": 4, "7": 20}, 1: {}}
    loaded = {0: [3], 1: [7]}
    assert POLICY.next_round(queues, loaded).assign == {3: 0, 7: 1, 5: 0}
    assert RayWeightedRounds(fill_busy=False).next_round(queues, loaded).assign == {3: 0, 7: 1}


def test_a_busy_node_does_not_take_a_domain_that_makes_the_round_longer():
    # 5's 15 rays would give node 0 25 against the busiest's 20: 5 waits for a later round
    plan = POLICY.next_round({0: {"3": 10, "5": 15, "7": 20}, 1: {}}, {0: [3], 1: [7]})
    assert plan.assign == {3: 0, 7: 1}


def test_unheld_domains_go_to_the_least_busy_nodes_first():
    # kept rays: node 0 12, node 1 3, node 2 20; 8 (9 rays) goes to node 1, 6 (8) to node 0
    queues = {0: {"1": 12, "2": 3, "4": 20, "8": 9, "6": 8}}
    plan = POLICY.next_round(queues, {0: [1], 1: [2], 2: [4]})
    assert plan.assign == {1: 0, 2: 1, 4: 2, 8: 1, 6: 0}


def test_an_empty_round_says_finished():
    assert POLICY.next_round({0: {}, 1: {}}, {0: [1], 1: [2]}) == Round({}, finished=True)


def test_one_waiting_ray_anywhere_is_not_finished():
    plan = POLICY.next_round({0: {}, 1: {"0": 1}}, {0: [], 1: []})
    assert plan == Round({0: 0}, finished=False)


def test_rays_start_on_the_node_that_made_them():
    from vastray.schedule.dynamic import image_plane_start

    assert image_plane_start(4, 2).tolist() == [2, 2, 2, 2]
