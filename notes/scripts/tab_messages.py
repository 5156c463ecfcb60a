"""Which messages navapp sends a tab, and which of them make viser's client redraw the 3D scene
(issue 50, item 7). A probe, not a test.

    python notes/scripts/tab_messages.py [N_TABS]

Runs ``navapp serve --edge 12 --k 12`` on the demo in this process (cache: $NAVAPP_CACHE or a
temporary one), counts every message viser queues, opens N tabs (default 2) in headless Chromium,
then prints the messages sent over 10 s of idling, after "Collect the whole sweep now", and
after a click on "Rigid". viser's client (1.1.1, client/src/messageQueue.ts) redraws for any
batch holding a message that is not GUI-only; GUI-only batches skip the frame.
"""
import collections
import os
import sys
import tempfile
import threading
import time

os.environ.setdefault("NAVAPP_CACHE", tempfile.mkdtemp())
from playwright.sync_api import sync_playwright  # noqa: E402
from viser import _messages  # noqa: E402
from viser.infra import _infra  # noqa: E402

N = int(sys.argv[1]) if len(sys.argv) > 1 else 2
# client/src/messageQueue.ts, typeSetGuiOnlyMessage, plus the GUI components' own messages
GUI_ONLY = {"GuiUpdateMessage", "GuiRemoveMessage", "GuiModalMessage", "GuiCloseModalMessage", "GuiPanelMessage",
            "GuiPanelRemoveMessage", "GuiSetPanelCollapsedMessage", "GuiSetPanelHeightMessage",
            "GuiSetPanelPositionMessage", "GuiSetPanelWidthMessage", "SetGuiPanelLabelMessage",
            "NotificationShowMessage", "NotificationUpdateMessage", "RemoveNotificationMessage"}
counts: collections.Counter = collections.Counter()
lock = threading.Lock()
orig = _infra.WebsockMessageHandler.queue_message


def counting(self, message):
    name = type(message).__name__
    gui = name in GUI_ONLY or isinstance(message, _messages._CreateGuiComponentMessage)
    with lock:
        counts[("gui" if gui else "SCENE", name)] += 1
    return orig(self, message)


_infra.WebsockMessageHandler.queue_message = counting


def show(what, since):
    with lock:
        now = counts.copy()
    d = now - since
    scene = {k[1]: v for k, v in d.items() if k[0] == "SCENE"}
    gui = sum(v for k, v in d.items() if k[0] == "gui")
    print(f"{what}: {sum(scene.values())} scene messages {dict(scene)}; {gui} GUI-only", flush=True)
    return now


if __name__ == "__main__":
    from navapp import cli

    port = 8939
    w = tempfile.mkdtemp()
    t = threading.Thread(target=cli.main, args=(["serve", "--port", str(port), "--edge", "12", "--k", "12",
                                                  "--session", w + "/sess"],), daemon=True)
    t.start()
    time.sleep(3)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
        pages = []
        for _ in range(N):
            pg = b.new_page(viewport={"width": 1366, "height": 768})
            for _ in range(600):
                try:
                    pg.goto(f"http://127.0.0.1:{port}")
                    break
                except Exception:
                    time.sleep(1)
            pages.append(pg)
        for pg in pages:
            pg.get_by_text("Ready.").first.wait_for(timeout=900_000)
        time.sleep(5)
        c = show("settled", collections.Counter())
        time.sleep(10)
        c = show("10 s idle", c)
        pages[0].get_by_role("button", name="Collect the whole sweep now").click(timeout=60_000)
        time.sleep(10)
        c = show("sweep collected (10 s)", c)
        time.sleep(10)
        c = show("10 s idle", c)
        pages[0].get_by_role("button", name="Rigid").click(timeout=60_000)
        time.sleep(15)
        c = show("'Rigid' clicked (15 s)", c)
        time.sleep(10)
        c = show("10 s idle", c)
        b.close()
    os._exit(0)
