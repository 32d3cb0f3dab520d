"""The test session's own footprint on disk: a passing test's ``tmp_path`` is removed when the test
ends. Each training test writes a checkpoint of about 165 MB (``checkpoint.checkpoint_bytes``); kept
until the session ended, the suite's folders grew past 11 GB and filled a CI disk part way through."""


def test_a_passing_tests_temporary_folder_is_removed_when_it_ends(request):
    assert request.config.getini("tmp_path_retention_policy") == "failed"

