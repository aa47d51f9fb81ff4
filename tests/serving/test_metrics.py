from carp.serving.metrics import ServerMetrics


def test_the_histogram_is_cumulative_and_counts_every_answered_request():
    metrics = ServerMetrics(requests=4, errors=1)
    for seconds in (0.0005, 0.003, 0.003, 7.0):
        metrics.observe_latency(seconds)
    text = metrics.render()
    assert "carp_serving_requests_total 4\n" in text
    assert "carp_serving_errors_total 1\n" in text
    assert 'carp_serving_request_seconds_bucket{le="0.001"} 1\n' in text
    assert 'carp_serving_request_seconds_bucket{le="0.005"} 3\n' in text
    assert 'carp_serving_request_seconds_bucket{le="2.5"} 3\n' in text
    assert 'carp_serving_request_seconds_bucket{le="+Inf"} 4\n' in text
    assert "carp_serving_request_seconds_count 4\n" in text
    assert "# TYPE carp_serving_request_seconds histogram" in text
