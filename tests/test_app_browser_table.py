"""The run table read at 1366 × 768 and 1600 × 1000 in Chromium (issue 50, item 4): every cell's
text stands apart from its neighbours' ("17.572.1 / 5.3" was max error and tumour errors run
together, "0.75" seconds and iterations). Same server and helpers as ``test_app_browser``."""

import os
from pathlib import Path

import pytest
from conftest import free_port
from test_app_browser import ARGS, BUDGET_S, CHROMIUM, ROW, Deadline, click_button, playwright, start_server, wait_text

GAP_PX = 6  # the least white space between two cells' text in a row


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    proc, url = start_server(free_port(), tmp_path_factory.mktemp("session"))
    yield {"url": url}
    proc.terminate()
    proc.wait(20)


def gaps(page) -> list:
    """Per row of the run table: the white space (px) between each cell's text and the next's."""
    return page.evaluate("""() => {
        const table = [...document.querySelectorAll('table')].find(t => t.innerText.includes('iterations'));
        if (!table) return null;
        return [...table.querySelectorAll('tr')].map(tr => {
            const boxes = [...tr.children].map(td => {
                const r = document.createRange(); r.selectNodeContents(td);
                const b = r.getBoundingClientRect();
                return b.width > 0 ? [b.left, b.right, td.innerText] : null;
            }).filter(b => b);
            const out = [];
            for (let i = 1; i < boxes.length; i++)
                out.push([boxes[i - 1][2], boxes[i][2], boxes[i][0] - boxes[i - 1][1]]);
            return out;
        });
    }""")


@pytest.mark.parametrize("view", [{"width": 1366, "height": 768}, {"width": 1600, "height": 1000}])
def test_the_run_tables_columns_stand_apart(server, view, tmp_path):
    deadline = Deadline(BUDGET_S + 600)  # the module's server starts cold
    shots = Path(os.environ.get("NAVAPP_SCREENSHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        page = deadline.open(browser.new_page(viewport=view))
        page.goto(server["url"])
        wait_text(page, r"Ready\.", deadline)
        if not gaps(page):
            click_button(page, "Collect the whole sweep now", deadline)
            click_button(page, "Rigid", deadline)
            wait_text(page, ROW.format("rigid"), deadline)
            click_button(page, "Deformable (all data)", deadline)
            wait_text(page, ROW.format(r"deformable, all data"), deadline)
        rows = gaps(page)
        assert rows and len(rows) >= 3, rows
        table = page.locator("table", has_text="iterations").first
        table.scroll_into_view_if_needed()
        table.screenshot(path=shots / f"run_table_{view['width']}.png")
        tight = [(a, b, round(g, 1)) for row in rows for a, b, g in row if g < GAP_PX]
        assert not tight, tight
        browser.close()
