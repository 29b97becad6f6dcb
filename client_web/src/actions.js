// The dashboard's buttons and keyboard shortcuts: screenshot, link, CSV export, saved views,
// opening files as a replay, and the key bindings the help dialog lists.

import { lookAlong, normalizeCamera } from "./camera.js";
import { openReplay, replayFiles } from "./api.js";
import { $, downloadBlob } from "./dom.js";
import { RENDER_DEFAULTS, SIGMA_SLIDER, clamp, diffRender, mergeRender } from "./params.js";
import { requestScreenshot, screenshotName } from "./screenshot.js";
import { readViewFile, viewFile, viewFileName } from "./viewfile.js";

export class DashboardActions {
  async screenshot() {
    if (this.screenshotBusy) return;
    const button = $("btn-screenshot");
    this.screenshotBusy = true;
    button.disabled = true;
    const [width, height] = this.viewport.fullSize();
    try {
      const blob = await requestScreenshot({
        token: this.token,
        session: this.welcome?.session_id ?? this.sessionName,
        width,
        height,
        params: this.render,
        camera: this.camera,
      });
      downloadBlob(blob, screenshotName(this.sessionName, this.sim?.step));
      this.notices.notify({ level: "info", code: "screenshot", message: `saved a ${width}×${height} PNG` });
    } catch (err) {
      this.notices.notify({ level: "error", code: "screenshot", message: err.message });
    } finally {
      this.screenshotBusy = false;
      button.disabled = false;
    }
  }

  async copyLink() {
    this.writeHash();
    const url = window.location.href;
    const what = this.role === "steerer" ? "steer" : "view";
    try {
      await navigator.clipboard.writeText(url);
      this.notices.notify({
        level: "info",
        code: "link",
        message: `link copied; it carries your token, so whoever opens it can ${what}`,
      });
    } catch {
      this.notices.notify({ level: "info", code: "link", message: `copy this link: ${url}` });
    }
  }

  exportCsv() {
    const blob = new Blob([this.plots.csv()], { type: "text/csv" });
    downloadBlob(blob, `scalesteer-${this.sessionName}-plots.csv`);
  }

  nudgeSigma(factor) {
    const sigma = clamp(Number((this.render.sigma_A * factor).toPrecision(3)), SIGMA_SLIDER.min, SIGMA_SLIDER.max);
    this.renderPanel.update({ ...this.render, sigma_A: sigma });
    this.steerRender({ sigma_A: sigma }, true);
  }

  nudgeIso(delta) {
    const iso = clamp(Number((this.render.iso_level + delta).toFixed(3)), 0.01, 100);
    this.renderPanel.update({ ...this.render, iso_level: iso });
    this.steerRender({ iso_level: iso }, true);
  }

  bindButtons() {
    $("btn-reset-view").addEventListener("click", () => this.resetView());
    $("btn-projection").addEventListener("click", () => this.toggleProjection());
    $("btn-screenshot").addEventListener("click", () => this.screenshot());
    $("btn-copy-link").addEventListener("click", () => this.copyLink());
    $("btn-help").addEventListener("click", () => this.shortcuts.open());
    $("btn-export-csv").addEventListener("click", () => this.exportCsv());
    $("btn-clear-plots").addEventListener("click", () => this.plots.clear());
    $("btn-reconnect").addEventListener("click", () => this.connection.reconnectNow());
    $("btn-save-view").addEventListener("click", () => this.saveView());
    $("btn-open-view").addEventListener("click", () => $("open-view-file").click());
    $("open-view-file").addEventListener("change", (e) => this.openView(e.target));
    $("btn-open-files").addEventListener("click", () => $("open-files").click());
    $("open-files").addEventListener("change", (e) => this.openFiles(e.target));
    $("plot-window").addEventListener("change", (e) => this.plots.setWindow(Number(e.target.value)));
    $("resolution").addEventListener("change", (e) => this.viewport.setResolution(Number(e.target.value)));
    $("transport").value = this.transport;
    $("transport").addEventListener("change", (e) => this.setTransport(e.target.value));
    $("pull-release-all").addEventListener("click", () => this.releaseAll());
    $("tf-preset").addEventListener("change", (e) =>
      this.steerRender({ tf_preset: e.target.value, transfer_function: [] }, true),
    );
    $("tf-reset").addEventListener("click", () =>
      this.steerRender({ tf_preset: this.render.tf_preset, transfer_function: [] }, true),
    );
  }

  saveView() {
    const session = this.welcome?.session_id ?? this.sessionName;
    const data = viewFile({ session, camera: this.camera, render: this.render, atoms: this.picks.indices });
    downloadBlob(new Blob([JSON.stringify(data, null, 2)], { type: "application/json" }), viewFileName(session));
    this.notices.notify({ level: "info", code: "view", message: "view saved" });
  }

  async openView(input) {
    const file = input.files?.[0];
    input.value = "";
    if (!file) return;
    let view;
    try {
      view = readViewFile(await file.text());
    } catch (err) {
      this.notices.notify({ level: "error", code: "view", message: `${file.name}: ${err.message}` });
      return;
    }
    if (view.camera) this.setCamera(normalizeCamera(view.camera), false);
    if (view.render) {
      if (this.role === "steerer") {
        const patch = diffRender(this.render, mergeRender(RENDER_DEFAULTS, view.render));
        if (Object.keys(patch).length) this.steerRender(patch, true);
        this.renderPanel.update(this.render);
        this.timePanel.update(this.render);
      } else {
        this.notices.notify({
          level: "info",
          code: "view",
          message: "the view's render settings need the steering token; only its camera was applied",
        });
      }
    }
    this.picks.atoms = view.atoms.map((atom) => ({ atom, name: `#${atom}` }));
    this.showPicks();
    this.sendView(false);
    this.notices.notify({ level: "info", code: "view", message: `opened ${file.name}` });
  }

  async openFiles(input) {
    const files = [...(input.files ?? [])];
    input.value = "";
    if (!files.length) return;
    try {
      replayFiles(files); // refused here, naming the files, before anything is uploaded
      this.notices.notify({
        level: "info",
        code: "open",
        message: `uploading ${files.map((f) => f.name).join(", ")}…`,
      });
      const opened = await openReplay({ token: this.token, files });
      const url = new URL(window.location.href);
      url.searchParams.set("session", opened.session);
      url.hash = "";
      window.location.assign(url.toString());
    } catch (err) {
      this.notices.notify({ level: "error", code: "open", message: err.message });
    }
  }

  bindings() {
    const steer = () => this.role === "steerer";
    return [
      { keys: ["?"], label: "?", description: "Show or hide this help", run: () => this.shortcuts.toggle() },
      {
        keys: ["r", "R"],
        label: "R",
        description: "Reset the view to the session's default camera",
        run: () => this.resetView(),
      },
      {
        keys: ["o", "O"],
        label: "O",
        description: "Toggle orthographic / perspective projection",
        run: () => this.toggleProjection(),
      },
      {
        keys: ["x"],
        label: "X / Y / Z",
        description: "View from +x, +y, +z (with Shift: from −x, −y, −z)",
        run: () => this.look("x"),
      },
      { keys: ["X"], hidden: true, run: () => this.look("-x") },
      { keys: ["y"], hidden: true, run: () => this.look("y") },
      { keys: ["Y"], hidden: true, run: () => this.look("-y") },
      { keys: ["z"], hidden: true, run: () => this.look("z") },
      { keys: ["Z"], hidden: true, run: () => this.look("-z") },
      {
        keys: ["["],
        label: "[ / ]",
        description: "Smaller / larger scale σ",
        run: () => this.nudgeSigma(1 / 1.15),
        when: steer,
      },
      { keys: ["]"], hidden: true, run: () => this.nudgeSigma(1.15), when: steer },
      {
        keys: [","],
        label: ", / .",
        description: "Lower / raise the iso level",
        run: () => this.nudgeIso(-0.05),
        when: steer,
      },
      { keys: ["."], hidden: true, run: () => this.nudgeIso(0.05), when: steer },
      {
        keys: ["m", "M"],
        label: "M",
        description: "Switch isosurface / volume mode",
        run: () => {
          const mode = this.render.mode === "iso" ? "volume" : "iso";
          this.renderPanel.update({ ...this.render, mode });
          this.steerRender({ mode }, true);
        },
        when: steer,
      },
      {
        keys: [" "],
        label: "Space",
        description: "Pause or resume the simulation",
        run: () => this.simPanel.togglePlay(),
        when: steer,
      },
      {
        keys: ["n", "N"],
        label: "N",
        description: "Advance the simulation by the step count",
        run: () => this.simPanel.step(),
        when: steer,
      },
      {
        keys: ["S"],
        label: "Shift+S",
        description: "Download a full-resolution screenshot",
        run: () => this.screenshot(),
      },
      { keys: ["l", "L"], label: "L", description: "Copy a link to this view", run: () => this.copyLink() },
      { keys: ["e", "E"], label: "E", description: "Export the plots as CSV", run: () => this.exportCsv() },
      {
        keys: ["v", "V"],
        label: "V",
        description: "Focus the live view (then arrows rotate, Shift+arrows pan, +/− zoom, Enter picks the centre)",
        run: () => $("view").focus(),
      },
      { keys: ["Escape"], label: "Esc", description: "Clear the selected atom", run: () => this.clearSelection() },
    ];
  }

  look(axis) {
    if (this.camera) this.setCamera(lookAlong(this.camera, axis), false);
  }
}
