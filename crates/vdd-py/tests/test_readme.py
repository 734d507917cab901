"""The README's Python quick start runs as written (in a temporary directory)."""

import pathlib
import re

README = pathlib.Path(__file__).resolve().parents[3] / "README.md"


def test_the_readme_python_snippet_runs(tmp_path, monkeypatch):
    text = README.read_text()
    section = text.split("## Python", 1)[1]
    snippet = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    exec(compile(snippet, "README.md", "exec"), {})
    assert (tmp_path / "policy.onnx").stat().st_size > 1000
    assert (tmp_path / "policy.safetensors").exists()
