// Admin console: users, scene import, frame selection (coverage curve + top-down map), jobs
// with live progress and log tails, exports with downloads, metric tables, class histograms.

import { api } from "../core/api.js";
import { el, showError, clearError, toast, pct, fmtDate, table, dialog, downloadBlob } from "../core/ui.js";
import { bytes, pathField, uploadControls, memberPicker, usersTable, confirmDeleteScene, exportsTable, overviewView } from "./console.js";
import { linePlot, barPlot, mapPlot, cellRect } from "./plots.js";

const ACTIVE = new Set(["queued", "running"]);

export async function mount(root, ctx) {
  const p = new AdminPage(root, ctx);
  await p.start();
  return p;
}

function section(id, title, ...children) {
  return el("section", { class: "card", id, "aria-labelledby": `${id}-h` }, el("h2", { id: `${id}-h` }, title), ...children);
}

function field(label, input, hint = null) {
  const id = input.id;
  return el("div", { class: "field" }, el("label", { for: id }, label), input, hint ? el("small", {}, hint) : null);
}

class AdminPage {
  constructor(root, ctx) {
    this.root = root;
    this.ctx = ctx;
    this.timer = null;
    this.qualityTimer = null;
    this.alive = true;
    this.jobs = [];
  }

  async start() {
    this.usersEl = el("div");
    this.scenesEl = el("div");
    this.selectionEl = el("div", { class: "plots" });
    this.nextEl = el("div", { id: "next-frames", "aria-live": "polite" }); // issue 37
    this.jobsEl = el("div", { id: "jobs" });
    this.exportsEl = el("div");
    this.qualityEl = el("div", { id: "quality" }); // issue 23: how the scene's labels were made
    this.liftingEl = el("div", { id: "lifting", "aria-live": "polite" }); // issue 37: annotator model
    this.liftingTimer = null;
    this.exportPlanEl = el("div", { id: "export-plan", "aria-live": "polite" });
    this.histEl = el("div");
    this.effortEl = el("div", { id: "effort" });
    this.membersEl = el("div", { id: "members" });
    this.auditEl = el("div", { id: "audit" });
    this.overviewEl = el("div", { id: "overview" }); // issue 28: across scenes and annotators
    this.exportListEl = el("div", { id: "export-list" });
    this.uploadsEl = el("div", { id: "uploads" }); // issue 36: uploaded project folders
    this.maskImportEl = el("div", { id: "mask-import-result", "aria-live": "polite" });
    this.sceneSel = el("select", { id: "admin-scene", "aria-label": "Scene" });
    this.sceneSel.addEventListener("change", () => {
      this.ctx.setParams({ scene: this.sceneSel.value });
      this.loadScene();
    });
    this.root.append(
      el(
        "div",
        { class: "admin" },
        el("div", { class: "row admin-head" }, el("h1", {}, "Admin console"), el("label", { for: "admin-scene" }, "Scene"), this.sceneSel),
        el(
          "nav",
          { class: "subnav", "aria-label": "Admin sections" },
          ["overview", "users", "scenes", "members", "selection", "masks", "jobs", "exports", "labels", "lifting", "quality", "effort", "audit"].map((s) => el("a", { href: `#/admin`, onclick: (e) => { e.preventDefault(); document.getElementById(`sec-${s}`)?.scrollIntoView(); } }, s)),
        ),
        section("sec-overview", "Overview", el("p", { class: "hint" }, "Every scene and annotator at a glance: frames to do (selected, not started), in progress, waiting for review, accepted and rejected; time spent, throughput and how far the 3D labels lag behind."), this.overviewEl),
        section("sec-users", "Users", this.usersEl, this.userForm()),
        section("sec-scenes", "Scenes", this.scenesEl, this.importForm(), el("h3", {}, "Uploaded projects"), this.uploadsEl),
        section("sec-members", "Scene members", el("p", { class: "hint" }, "Annotators and reviewers see only the scenes they are members of."), this.membersEl),
        section("sec-selection", "Frame selection", this.selectionForm(), this.selectionEl, this.nextForm(), this.nextEl),
        section("sec-masks", "Masks from other tools", el("p", { class: "hint" }, "Upload masks painted in CVAT, COCO, Label Studio or as PNGs (a zip of the tool's export). Every frame they paint gets an imported version that votes and waits for review; if a class or an image name does not match the scene, nothing is stored and every problem is listed."), this.maskImportForm(), this.maskImportEl, this.maskExportForm()),
        section("sec-jobs", "Jobs", this.jobsEl),
        section("sec-exports", "Exports and metrics", this.exportForm(), this.exportListEl, this.exportsEl),
        section("sec-labels", "Labels: class histogram", this.histEl),
        section("sec-lifting", "Lifting: how the votes are decided", el("p", { class: "hint" }, "Every saved mask votes for its classes on the 3D points it sees; the live lifting decides each point from those votes. Who painted which mask is known here, so a painter who systematically swaps two look-alike classes can be told apart from the others. Changing the model fills the scene's labels again at once."), this.liftingEl),
        section("sec-quality", "Quality", el("p", { class: "hint" }, "How the scene's live labels were made: each annotated frame's votes against the labels the other frames give without it (leave-one-out agreement), how much of it other frames see, points seen by two or more frames, points whose votes disagree, and the calibrated confidence. An export writes the same report as quality.json beside its data."), this.qualityEl),
        section("sec-effort", "Annotation effort", el("p", { class: "hint" }, "Per submitted mask, in submission order: the share of the frame's pixels painted (what painting from an empty mask costs) and the share that differs from the 3D prefill its annotator started from."), this.effortEl),
        section("sec-audit", "Audit log", this.auditForm(), this.auditEl),
      ),
    );
    await Promise.all([this.loadUsers(), this.loadScenes(), this.loadOverview(), this.loadExportList(), this.loadUploads()]);
    await this.loadScene();
    this.loadAudit();
    this.poll();
  }

  unmount() {
    this.alive = false;
    clearTimeout(this.timer);
    clearTimeout(this.qualityTimer);
    clearTimeout(this.liftingTimer);
  }

  get sid() {
    return this.sceneSel.value;
  }

  async guard(fn) {
    try {
      return await fn();
    } catch (e) {
      showError(e);
      return null;
    }
  }

  // ---- uploaded project folders (issue 36) ----------------------------------------------
  async loadUploads() {
    const ups = await this.guard(() => api.get("/imports/uploads"));
    if (!ups) return;
    if (!ups.length) {
      this.uploadsEl.replaceChildren(el("p", { class: "hint" }, "No project uploaded as a zip is kept on the server."));
      return;
    }
    const del = (u) => {
      if (u.scenes.length) return el("span", { class: "muted" }, `used by scene ${u.scenes.join(", ")}`);
      const b = el("button", { type: "button", class: "danger", "aria-label": `Delete upload ${u.name}` }, "Delete");
      b.addEventListener("click", async () => {
        const ok = await dialog({ title: `Delete upload ${u.name}?`, body: el("p", {}, `${u.files} files, ${bytes(u.bytes)} are removed from the server. No scene imports from it.`), buttons: [{ label: "Cancel", value: false }, { label: "Delete", value: true, primary: true }], cancelValue: false });
        if (!ok) return;
        b.disabled = true; // a double click deletes once
        const res = await this.guard(() => api.send("DELETE", `/imports/uploads/${encodeURIComponent(u.name)}`));
        if (res) toast(`Upload ${u.name} deleted.`);
        this.loadUploads();
      });
      return b;
    };
    this.uploadsEl.replaceChildren(
      table(ups, [
        { key: "name", label: "Upload" },
        { key: "files", label: "Files" },
        { key: "bytes", label: "Size", fmt: (v) => bytes(v) },
        { key: "modified", label: "Uploaded", fmt: (v) => fmtDate(new Date(v * 1000).toISOString()) },
        { key: "scenes", label: "", fmt: (_v, u) => del(u) },
      ], { rowAttrs: (u) => ({ "data-upload": u.name }) }),
    );
  }

  // ---- users ---------------------------------------------------------------------------
  async loadUsers() {
    await this.guard(async () => {
      const users = (await api.get("/users")) || [];
      this.users = users;
      this.usersEl.replaceChildren(usersTable(users, this.ctx.session && this.ctx.session.user, () => this.loadUsers()));
      this.memberPickerEl?.replaceWith((this.memberPickerEl = memberPicker(users)));
    });
  }

  userForm() {
    const name = el("input", { id: "new-username", required: true, autocomplete: "off" });
    const pw = el("input", { id: "new-password", type: "password", required: true, autocomplete: "new-password", minlength: 8 });
    const role = el("select", { id: "new-role" }, ["annotator", "reviewer", "admin"].map((r) => el("option", { value: r }, r)));
    const f = el("form", { class: "inline-form", "aria-label": "Create user" }, field("User name", name), field("Password", pw), field("Role", role), el("button", { type: "submit" }, "Create user"));
    f.addEventListener("submit", async (e) => {
      e.preventDefault();
      const r = await this.guard(() => api.post("/users", { username: name.value.trim(), password: pw.value, role: role.value }));
      if (r) {
        toast(`User ${name.value} created.`);
        f.reset();
        this.loadUsers();
      }
    });
    return f;
  }

  // ---- scenes ----------------------------------------------------------------------------
  async loadScenes() {
    await this.guard(async () => {
      const [scenes, st] = await Promise.all([api.get("/scenes"), api.get("/storage").catch(() => null)]);
      this.scenes = scenes || [];
      const used = new Map(((st && st.scenes) || []).map((s) => [s.scene_id, s]));
      const keep = this.sceneSel.value || this.ctx.params.scene;
      this.sceneSel.replaceChildren(...scenes.map((s) => el("option", { value: s.id }, s.name)));
      if (keep && scenes.some((s) => String(s.id) === String(keep))) this.sceneSel.value = keep;
      this.scenesEl.replaceChildren(
        scenes.length
          ? table(scenes, [
              { key: "name", label: "Scene" },
              { key: "status", label: "Status" },
              { key: "n_frames", label: "Frames" },
              { key: "n_points", label: "Points", fmt: (v) => (v == null ? "" : Number(v).toLocaleString()) },
              { key: "n_selected", label: "Selected" },
              { key: "coverage", label: "Coverage", fmt: (v) => pct(v) },
              { key: "created_at", label: "Imported", fmt: fmtDate },
              { key: "id", label: "Storage", fmt: (v) => (used.has(v) ? el("span", { class: "storage", title: `workspace ${bytes(used.get(v).workspace_bytes)}, exports ${bytes(used.get(v).export_bytes)}, masks ${bytes(used.get(v).mask_bytes)}, cached images ${bytes(used.get(v).cache_bytes)}` }, bytes(used.get(v).total_bytes)) : "–") },
              { key: "id", label: "", fmt: (_v, s) => el("button", { type: "button", class: "small danger scene-delete", "aria-label": `Delete scene ${s.name}`, onclick: async () => { if (await confirmDeleteScene(s)) { this.loadScenes().then(() => this.loadScene()); this.loadOverview(); this.loadExportList(); } } }, "Delete") },
            ], { rowAttrs: (s) => ({ "data-scene": s.name }) })
          : el("p", {}, "No scenes yet: import one below."),
        st ? el("p", { class: "muted", id: "storage-summary" }, `Scenes take ${bytes(st.total_bytes)}; the data disk has ${bytes(st.disk.free_bytes)} free of ${bytes(st.disk.total_bytes)}. Export retention: ${st.retention.keep_last ? `newest ${st.retention.keep_last} per scene` : "keep all"}${st.retention.max_age_days ? `, at most ${st.retention.max_age_days} days` : ""}.`) : null,
      );
    });
  }

  importForm() {
    const name = el("input", { id: "imp-name", required: true });
    const source = el("input", { id: "imp-source", required: true, placeholder: "/data/surveys/site_01" });
    const cloud = el("input", { id: "imp-cloud", placeholder: "optional: dense cloud (.ply/.las/.laz)" });
    const depth = el("input", { id: "imp-depth", placeholder: "optional: depth map folder" });
    // the project kinds occufly import reads (the server detects the kind when left on auto)
    const kind = el(
      "select",
      { id: "imp-format" },
      el("option", { value: "" }, "detect from the files"),
      el("option", { value: "colmap" }, "COLMAP model / dense workspace"),
      el("option", { value: "odm" }, "OpenDroneMap / WebODM project"),
      el("option", { value: "metashape" }, "Agisoft Metashape camera XML"),
      el("option", { value: "pix4d" }, "Pix4D project"),
    );
    const images = el("input", { id: "imp-images", placeholder: "optional: image folder (default: images/)" });
    const crs = el("input", { id: "imp-crs", placeholder: "optional: cloud CRS if its file has none, e.g. EPSG:32632" });
    const scale = el("input", { id: "imp-scale", type: "number", min: "0", step: "any",
                                placeholder: "COLMAP without GPS: metres per model unit (1 if metric)" });
    const f = el(
      "form",
      { class: "inline-form", "aria-label": "Import a scene" },
      field("Name", name),
      pathField("Reconstruction folder", source, "inside an allowed import root on the server: Browse… lists them", { pick: "any" }),
      uploadControls(name, (r) => {
        this.loadUploads();
        source.value = r.source;
        if (!name.value.trim()) name.value = r.source.split("/").pop().replace(/[^A-Za-z0-9_.-]/g, "_");
      }),
      field("Kind", kind, "Metashape: the exported cameras .xml; ODM/Pix4D: the project folder"),
      pathField("Cloud", cloud, null, { pick: "file", title: "Choose the dense cloud" }),
      pathField("Images", images),
      pathField("Depth maps", depth),
      (this.memberPickerEl = memberPicker(this.users || [])),
      field("CRS", crs),
      field("Scale", scale, "only for a COLMAP model that is neither georeferenced nor geotagged"),
      el("button", { type: "submit" }, "Import"),
    );
    f.addEventListener("submit", async (e) => {
      e.preventDefault();
      const body = { name: name.value.trim(), source: source.value.trim() };
      if (cloud.value.trim()) body.cloud = cloud.value.trim();
      if (depth.value.trim()) body.depth_maps = depth.value.trim();
      if (kind.value) body.format = kind.value;
      if (images.value.trim()) body.images = images.value.trim();
      if (crs.value.trim()) body.crs = crs.value.trim();
      if (scale.value.trim()) body.scale = Number(scale.value);
      const members = this.memberPickerEl ? this.memberPickerEl.selected() : [];
      if (members.length) body.members = members;
      const job = await this.guard(() => api.post("/scenes/import", body));
      if (job) {
        clearError(); // an earlier refusal no longer applies
        toast(`Import job ${job.id} started.`);
        this.track(job);
      }
    });
    return f;
  }

  // ---- masks from other tools (issue 26) -----------------------------------------------------
  maskImportForm() {
    const file = el("input", { id: "mi-archive", type: "file", required: true, accept: ".zip,.json,.xml" });
    // the formats occufly.io.mask_interchange reads (server side: Datumaro, pycocotools, Label Studio's codec)
    const format = el(
      "select",
      { id: "mi-format" },
      el("option", { value: "cvat" }, "CVAT (for images 1.1 or Segmentation mask 1.1)"),
      el("option", { value: "coco" }, "COCO instances (polygons / RLE)"),
      el("option", { value: "coco_panoptic" }, "COCO panoptic"),
      el("option", { value: "labelstudio" }, "Label Studio JSON (brush / polygons)"),
      el("option", { value: "png" }, "PNG masks + class map"),
    );
    const mapping = el("input", { id: "mi-mapping", type: "file", accept: ".json,.yaml,.yml" });
    const author = el("input", { id: "mi-author", maxlength: "40", placeholder: "optional: who painted them (recorded in the source)" });
    const f = el(
      "form",
      { class: "inline-form", "aria-label": "Import masks from another tool" },
      field("Archive", file, "the tool's export, zipped"),
      field("Format", format),
      field("Class mapping", mapping, "optional JSON/YAML {their class: our class} where names differ"),
      field("Author", author),
      el("button", { type: "submit" }, "Import masks"),
    );
    f.addEventListener("submit", async (e) => {
      e.preventDefault();
      if (!this.sid || !file.files.length) return;
      const body = new FormData();
      body.append("archive", file.files[0]);
      body.append("format", format.value);
      if (mapping.files.length) body.append("mapping", mapping.files[0]);
      if (author.value.trim()) body.append("author", author.value.trim());
      this.maskImportEl.replaceChildren(el("p", { class: "hint" }, "Reading the archive…"));
      try {
        const res = await api.send("POST", `/scenes/${this.sid}/masks/import`, { body });
        this.showMaskImport(await res.json(), file.files[0].name);
        toast("Masks imported.");
        this.loadScene();
      } catch (err) {
        const problems = (err && err.body && err.body.problems) || [err.message || String(err)];
        this.maskImportEl.replaceChildren(
          el("div", { class: "alert", role: "alert", style: { display: "block" } },
            el("strong", {}, `Nothing imported from ${file.files[0].name}:`),
            el("ul", {}, problems.map((p) => el("li", {}, p)))),
        );
      }
    });
    return f;
  }

  maskExportForm() {
    const format = el(
      "select",
      { id: "mx-format" },
      el("option", { value: "cvat" }, "CVAT for images 1.1"),
      el("option", { value: "cvat_mask" }, "CVAT Segmentation mask 1.1"),
      el("option", { value: "coco" }, "COCO instances"),
      el("option", { value: "coco_panoptic" }, "COCO panoptic"),
      el("option", { value: "labelstudio" }, "Label Studio JSON"),
      el("option", { value: "png" }, "PNG masks"),
    );
    const what = el(
      "select",
      { id: "mx-what" },
      el("option", { value: "prefill" }, "3D prefill of the selected frames (pre-annotations)"),
      el("option", { value: "masks" }, "the masks that count (one per frame)"),
    );
    const f = el(
      "form",
      { class: "inline-form", "aria-label": "Download masks for another tool" },
      field("Download", what),
      field("as", format),
      el("button", { type: "submit" }, "Download zip"),
    );
    f.addEventListener("submit", async (e) => {
      e.preventDefault();
      if (!this.sid) return;
      const res = await this.guard(() => api.send("GET", `/scenes/${this.sid}/masks/export?format=${format.value}&what=${what.value}`));
      if (res) downloadBlob(await res.blob(), `scene${this.sid}_${what.value}_${format.value}.zip`);
    });
    return f;
  }

  showMaskImport(r, name) {
    const classes = Object.entries(r.classes).map(([k, v]) => `${k} → ${v}`).join(", ");
    this.maskImportEl.replaceChildren(
      el("p", {}, el("strong", {}, `${r.frames_imported} frame(s) imported`), ` from ${name} (${r.format}); source “${r.source}”.`),
      el("p", { class: "hint" }, `Classes: ${classes}.`, r.skipped_without_annotations.length ? ` Skipped (nothing painted): ${r.skipped_without_annotations.join(", ")}.` : "",
        r.unchanged && r.unchanged.length ? ` Unchanged (already their current mask): ${r.unchanged.join(", ")}.` : ""),
      table(r.frames, [
        { key: "frame", label: "Frame" },
        { key: "item", label: "Image in the archive" },
        { key: "number", label: "Version of the frame", fmt: (v, f) => el("span", { class: "mi-version", "data-version": f.version, title: `version id ${f.version} (ids count across all frames)` }, v != null ? `v${v}` : `id ${f.version}`) },
        { key: "kind", label: "State" },
      ], { caption: "Imported versions (they wait for review)" }),
    );
  }

  async loadScene() {
    if (!this.sid) return;
    // metrics only once the jobs say an evaluation finished (else the API answers 404)
    await Promise.all([this.loadSelection(), this.loadJobs().then(() => this.loadMetrics()), this.loadHistogram(), this.loadEffort(), this.loadMembers(), this.loadQuality(), this.loadExportPlan(), this.loadLifting()]);
  }

  // ---- overview, exports on disk (issue 28) --------------------------------------------------
  async loadOverview() {
    await this.guard(async () => {
      this.overviewEl.replaceChildren(overviewView(await api.get("/overview")));
    });
  }

  async loadExportList() {
    await this.guard(async () => {
      const rows = (await api.get("/exports")) || [];
      this.exportListEl.replaceChildren(el("h3", {}, "Exports on disk"), exportsTable(rows, () => { this.loadExportList(); this.loadScenes(); this.loadJobs(); this.loadOverview(); }));
    });
  }

  // ---- scene members -------------------------------------------------------------------------
  async loadMembers() {
    const sid = this.sid;
    await this.guard(async () => {
      const [members, users] = await Promise.all([api.get(`/scenes/${sid}/members`), api.get("/users")]);
      if (sid !== this.sid) return;
      const ids = new Set((members || []).map((m) => m.user_id));
      const candidates = (users || []).filter((u) => u.role !== "admin" && !ids.has(u.id));
      const pick = el("select", { id: "member-add", "aria-label": "User to add" }, candidates.map((u) => el("option", { value: u.id }, `${u.username} (${u.role})`)));
      const add = el("button", { type: "submit", disabled: !candidates.length }, "Add member");
      const f = candidates.length
        ? el("form", { class: "inline-form", "aria-label": "Add scene member" }, pick, add)
        : el("p", { class: "hint" }, "Every annotator and reviewer is a member of this scene.");
      f.addEventListener("submit", async (e) => {
        e.preventDefault();
        if (await this.guard(() => api.post(`/scenes/${sid}/members`, { user_ids: [Number(pick.value)] }))) {
          toast("Member added.");
          this.loadMembers();
        }
      });
      const remove = (m) =>
        el("button", {
          class: "small",
          "aria-label": `Remove ${m.username}`,
          onclick: async () => {
            if (await this.guard(() => api.send("DELETE", `/scenes/${sid}/members/${m.user_id}`))) {
              toast(`${m.username} removed from the scene.`);
              this.loadMembers();
            }
          },
        }, "Remove");
      this.membersEl.replaceChildren(
        members && members.length
          ? table(members, [
              { key: "username", label: "User" },
              { key: "role", label: "Role" },
              { key: "active", label: "Active", fmt: (v) => (v ? "yes" : "deactivated") },
              { key: "user_id", label: "", fmt: (_v, m) => remove(m) },
            ])
          : el("p", { class: "hint" }, "No members yet: annotators and reviewers cannot see this scene."),
        f,
      );
    });
  }

  // ---- audit log ---------------------------------------------------------------------------
  auditForm() {
    this.auditAction = el("input", { id: "audit-action", placeholder: "e.g. login,mask_save", pattern: "[a-z_,]*", autocomplete: "off" });
    this.auditScene = el("input", { id: "audit-scene", type: "checkbox" });
    const f = el("form", { class: "inline-form", "aria-label": "Filter audit log" }, field("Actions", this.auditAction, "comma-separated; empty = all"), el("label", {}, this.auditScene, " this scene only"), el("button", { type: "submit" }, "Show"));
    f.addEventListener("submit", (e) => {
      e.preventDefault();
      this.loadAudit();
    });
    return f;
  }

  async loadAudit({ before = null } = {}) {
    await this.guard(async () => {
      const q = new URLSearchParams({ limit: "50" });
      const action = this.auditAction.value.trim();
      if (action) q.set("action", action);
      if (this.auditScene.checked && this.sid) q.set("scene_id", this.sid);
      if (before) q.set("before_id", before);
      const events = (await api.get(`/audit?${q}`)) || [];
      const rows = before ? [...(this.auditRows || []), ...events] : events;
      this.auditRows = rows;
      const more = events.length === 50 ? el("button", { type: "button", onclick: () => this.loadAudit({ before: events[events.length - 1].id }) }, "Older events") : null;
      this.auditEl.replaceChildren(
        rows.length
          ? table(rows, [
              { key: "at", label: "When", fmt: fmtDate },
              { key: "actor", label: "Who", fmt: (v) => v ?? "–" },
              { key: "action", label: "Action" },
              { key: "scene_name", label: "Scene", fmt: (v, r) => v ?? (r.scene_id != null ? `#${r.scene_id} (deleted)` : "") },
              { key: "frame_name", label: "Frame", fmt: (v, r) => v ?? (r.frame_id != null ? `#${r.frame_id} (deleted)` : "") },
              { key: "target", label: "Target", fmt: (v) => v ?? "" },
              { key: "users", label: "Users", fmt: (v) => Object.values(v || {}).join(", ") },
              { key: "client_ip", label: "Address", fmt: (v) => v ?? "" },
            ], { caption: `${rows.length} event(s), newest first` })
          : el("p", { class: "hint" }, "No events match."),
        ...(more ? [more] : []),
      );
    });
  }

  // ---- selection ---------------------------------------------------------------------------
  selectionForm() {
    this.selCell = el("input", { id: "sel-cell", type: "number", min: 1, step: "any", value: 25 });
    this.selMode = el("select", { id: "sel-mode" }, ["stratified", "greedy"].map((m) => el("option", { value: m }, m)));
    this.selTarget = el("input", { id: "sel-target", type: "number", min: 0, max: 1, step: 0.01, value: 0.99 });
    this.selAlt = el("input", { id: "sel-alt", type: "number", step: "any", placeholder: "all" });
    // "auto": the server tries 23–28 m and keeps the fewest frames reaching the target (greedy only)
    this.selAuto = el("input", { id: "sel-auto", type: "checkbox" });
    const syncAuto = () => {
      this.selCell.disabled = this.selAuto.checked;
      if (this.selAuto.checked) this.selMode.value = "greedy";
    };
    this.selAuto.addEventListener("change", syncAuto);
    this.selMode.addEventListener("change", () => {
      if (this.selMode.value !== "greedy") this.selAuto.checked = false;
      syncAuto();
    });
    this.syncAuto = syncAuto;
    const f = el(
      "form",
      { class: "inline-form", "aria-label": "Selection parameters" },
      field("Cell edge (m)", this.selCell, "23–28 m in the paper"),
      field("Best cell", this.selAuto, "greedy: try 23–28 m, keep the fewest frames"),
      field("Mode", this.selMode),
      field("Target coverage", this.selTarget),
      field("Altitude (m)", this.selAlt, "empty = all altitudes"),
      el("button", { type: "submit" }, "Run selection"),
    );
    f.addEventListener("submit", async (e) => {
      e.preventDefault();
      const body = { cell: this.selAuto.checked ? "auto" : Number(this.selCell.value), mode: this.selMode.value, target_coverage: Number(this.selTarget.value) };
      if (this.selAlt.value) body.altitude = Number(this.selAlt.value);
      const job = await this.guard(() => api.post(`/scenes/${this.sid}/selection`, body));
      if (job) {
        toast(`Selection job ${job.id} started.`);
        this.track(job, () => this.loadSelection({ force: true }));
      }
    });
    return f;
  }

  // issue 37: after a first round of masks, the frames whose masks would most settle the
  // contested and uncertain labels (a job; its result lists each frame with why)
  nextForm() {
    this.nextK = el("input", { id: "next-k", type: "number", min: 1, max: 200, step: 1, value: 5 });
    const btn = el("button", { type: "submit", id: "next-run" }, "Propose frames");
    const f = el(
      "form",
      { class: "inline-form", "aria-label": "Propose more frames to paint" },
      field("Propose more frames to paint", this.nextK, "frames without a mask that see the most contested / uncertain points"),
      btn,
    );
    f.addEventListener("submit", async (e) => {
      e.preventDefault();
      const k = Math.round(Number(this.nextK.value));
      if (!(k >= 1 && k <= 200)) return showError("Propose: the number of frames must be 1 to 200.");
      if (btn.disabled) return; // a double click starts one job
      btn.disabled = true;
      this.nextEl.replaceChildren(el("p", { class: "hint" }, "Weighing the frames…"));
      const job = await this.guard(() => api.post(`/scenes/${this.sid}/next-frames`, { k }));
      if (!job) {
        btn.disabled = false;
        this.nextEl.replaceChildren();
        return;
      }
      this.track(job, (done) => {
        btn.disabled = false;
        this.showNext(done);
      });
    });
    return f;
  }

  showNext(job) {
    if (job.status !== "done" || !job.result) {
      this.nextEl.replaceChildren(el("p", { class: "hint" }, `No proposal: ${job.message || job.status}.`));
      return;
    }
    const r = job.result;
    if (!r.frames?.length) {
      this.nextEl.replaceChildren(el("p", { id: "next-summary" }, `No frame proposed: ${r.message}.`));
      return;
    }
    const rows = (r.reasons || []).map((w, i) => ({ ...w, rank: i + 1 }));
    this.nextEl.replaceChildren(
      el("p", { id: "next-summary" }, `${r.frames.length} frames proposed: ${r.contested_points} contested and ${r.uncertain_points} uncertain points in the scene, ${r.annotated_frames} frames painted so far.`),
      table(rows, [
        { key: "rank", label: "#" },
        { key: "frame_name", label: "frame" },
        { key: "contested_points", label: "contested points it sees" },
        { key: "uncertain_points", label: "uncertain points it sees" },
        { key: "classes", label: "their classes", fmt: (v) => Object.entries(v || {}).map(([c, n]) => `${c} ${n}`).join(", ") },
        { key: "suspects", label: "suspects it sees", fmt: (v) => (v?.length ? String(v.length) : "–") },
      ], { caption: "Frames to paint next, best first" }),
    );
  }

  async loadSelection({ force = false } = {}) {
    const sid = this.sid;
    let sel = null;
    // a scene without selected frames has no selection to ask for (the API would answer 404)
    const sc = (this.scenes || []).find((x) => String(x.id) === String(sid));
    const known = force || !sc || sc.n_selected > 0;
    try {
      if (known) sel = await api.get(`/scenes/${sid}/selection`);
    } catch (e) {
      if (e.status !== 404) showError(e);
    }
    if (!sel) {
      this.selectionEl.replaceChildren(el("p", {}, "No selection yet for this scene."));
      return;
    }
    // the curve starts at the stratified set (n > 0): no invented (0, 0) point before it
    const curve = (sel.curve || []).map((p) => (Array.isArray(p) ? p : [p.n, p.coverage]));
    const nSel = Array.isArray(sel.frames) ? sel.frames.length : sel.selected;
    // show the parameters of the selection on display in the form
    const prm = sel.params || sel;
    this.selAuto.checked = prm.cell === "auto";
    if (sel.cell != null) this.selCell.value = sel.cell; // the edge used (the one chosen for "auto")
    if (prm.mode) this.selMode.value = prm.mode;
    this.syncAuto();
    if (prm.target_coverage != null) this.selTarget.value = prm.target_coverage;
    this.selAlt.value = prm.altitude ?? "";
    const curveC = el("canvas", { id: "coverage-plot" });
    const mapC = el("canvas", { id: "camera-map" });
    // `frames` are frame indices into the scene (the order of `cameras`).
    const selected = new Set((Array.isArray(sel.frames) ? sel.frames : []).map((v) => (typeof v === "object" ? v.index : v)));
    // Cells: a list of cell geometries ([x0, y0, x1, y1], {center, size}, ...), or occupied
    // grid indices with the grid origin (`occupied_cells` + `cell_origin`, what occufly.selection
    // reports); older results carry only the number of occupied cells and draw none.
    const edge = sel.cell ?? Number(this.selCell.value);
    let cells = Array.isArray(sel.cells) ? sel.cells.map((c) => cellRect(c, edge)).filter(Boolean) : [];
    if (!cells.length && Array.isArray(sel.occupied_cells) && Array.isArray(sel.cell_origin)) {
      const [ox, oy] = sel.cell_origin;
      cells = sel.occupied_cells.map(([i, j]) => ({ x0: ox + i * edge, y0: oy + j * edge, x1: ox + (i + 1) * edge, y1: oy + (j + 1) * edge }));
    }
    const lattice = null;
    this.selectionEl.replaceChildren(
      el(
        "p",
        { id: "selection-summary" },
        `${nSel ?? "?"} frames selected (${pct(sel.ratio)} of ${sel.candidates ?? "all"} candidates), coverage ${pct(sel.coverage, 2)}${sel.max_coverage != null ? ` of at most ${pct(sel.max_coverage, 2)}` : ""}; mode ${sel.mode ?? "?"}, cell ${edge} m${typeof sel.cells === "number" ? `, ${sel.cells} occupied cells` : ""}.`,
      ),
      el("div", { class: "row wrap" }, el("figure", {}, curveC, el("figcaption", {}, "Coverage vs number of selected frames")), el("figure", {}, mapC, el("figcaption", {}, cells.length ? "Top-down map: cameras (blue), selected frames (red), occupied grid cells" : `Top-down map: cameras (blue), selected frames (red); the API sent no cell geometry (${typeof sel.cells === "number" ? sel.cells : "?"} occupied cells of ${edge} m)`))),
    );
    // the greedy additions draw a line; a final pruning step (fewer frames, same coverage)
    // is the red marker only, not a line drawn back to the left
    let grow = curve.length;
    for (let i = 1; i < curve.length; i++) if (curve[i][0] < curve[i - 1][0]) { grow = i; break; }
    const line = curve.slice(0, grow);
    linePlot(curveC, line.length ? line : curve, { xLabel: "frames", yLabel: "coverage", xMin: 0, yMin: 0, yMax: 1, dots: true, marker: curve.length ? curve[curve.length - 1] : null, markerLabel: curve.length ? `${curve[curve.length - 1][0]} frames${grow < curve.length ? " after pruning" : ""}` : "", yFmt: (v) => `${Math.round(v * 100)}%` });
    mapPlot(mapC, { cameras: sel.cameras || [], selected, cells, lattice });
  }

  // ---- jobs ----------------------------------------------------------------------------------
  async loadJobs() {
    const sid = this.sid;
    const jobs = await api.get(`/jobs${sid ? `?scene_id=${sid}` : ""}`).catch((e) => {
      showError(e);
      return null;
    });
    if (!jobs || sid !== this.sid) return;
    // a job started while this list was on its way (a click during the page's load) is not in
    // it: keep tracking it, or its card and its callback (the next-frames table, ...) are lost
    const known = new Set(jobs.map((j) => j.id));
    const started = this.jobs.filter((j) => !known.has(j.id) && ACTIVE.has(j.status) && (!sid || String(j.scene_id) === String(sid)));
    this.jobs = [...started, ...jobs];
    this.renderJobs();
  }

  renderJobs() {
    const jobs = [...this.jobs].sort((a, b) => String(b.created_at).localeCompare(String(a.created_at)) || b.id - a.id);
    if (!jobs.length) {
      this.jobsEl.replaceChildren(el("p", {}, "No jobs yet."));
      return;
    }
    this.jobsEl.replaceChildren(
      el(
        "ul",
        { class: "jobs" },
        jobs.map((j) =>
          el(
            "li",
            { class: `job status-${j.status}`, "data-job": j.id, "data-status": j.status },
            el(
              "div",
              { class: "row" },
              el("strong", {}, `#${j.id} ${j.kind}`),
              el("span", { class: "badge" }, j.status),
              el("progress", { max: 1, value: j.progress ?? 0, "aria-label": `job ${j.id} progress` }),
              el("span", {}, `${Math.round(100 * (j.progress ?? 0))} %`),
              el("span", { class: "muted" }, j.message || ""),
              exportTook(j),
              el("span", { class: "spacer" }),
              ACTIVE.has(j.status) ? el("button", { type: "button", onclick: () => this.jobAction(j, "cancel") }, "Cancel") : null,
              ["interrupted", "failed", "cancelled"].includes(j.status) ? el("button", { type: "button", onclick: () => this.jobAction(j, "resume") }, "Resume") : null,
              j.kind === "export" && j.status === "done" ? (j.result && j.result.deleted_at ? el("span", { class: "muted export-deleted", "data-job": j.id }, `export deleted ${fmtDate(j.result.deleted_at)}: nothing to download`) : this.archiveControls(j)) : null,
            ),
            j.log_tail && j.log_tail.length ? el("details", { open: ACTIVE.has(j.status) || j.status === "failed" }, el("summary", {}, "log"), el("pre", { class: "log" }, j.log_tail.join("\n"))) : null,
          ),
        ),
      ),
    );
  }

  /** Compressed archive of an export: pick zip / tar.gz, build it, see its size, then save. */
  archiveControls(j) {
    this.archives ||= new Map();
    const st = this.archives.get(j.id) || { format: "tar.gz", info: null, busy: false };
    this.archives.set(j.id, st);
    const fmt = el("select", { "aria-label": `archive format of job ${j.id}`, class: "archive-format" }, ["tar.gz", "zip"].map((f) => el("option", { value: f }, f)));
    fmt.value = st.format;
    fmt.addEventListener("change", () => {
      st.format = fmt.value;
      st.info = null;
      this.renderJobs();
      this.archiveInfo(j.id);
    });
    const mb = (b) => (b >= 1e9 ? `${(b / 1e9).toFixed(2)} GB` : b >= 1e6 ? `${(b / 1e6).toFixed(1)} MB` : `${(b / 1e3).toFixed(0)} kB`);
    const i = st.info;
    let action;
    if (st.busy) action = el("span", { class: "muted" }, "Compressing…");
    else if (i && i.ready) action = el("a", { href: i.url, class: "button primary archive-link", download: i.name, "data-bytes": i.archive_bytes }, `Save ${i.name} · ${mb(i.archive_bytes)}`);
    else action = el("button", { type: "button", class: "archive-build", onclick: () => this.buildArchive(j.id) }, `Compress (${fmt.value})`);
    if (!i && !st.busy && !st.asked) {
      st.asked = true;
      this.archiveInfo(j.id);
    }
    return el(
      "span",
      { class: "archive", "data-job": j.id },
      fmt,
      action,
      i ? el("span", { class: "muted archive-content" }, `${i.files} files, ${mb(i.content_bytes)} before compression${i.ready ? `; archive ${mb(i.archive_bytes)}` : ""}`) : null,
    );
  }

  async archiveInfo(jid) {
    const st = this.archives.get(jid);
    let gone = false;
    const info = await api.get(`/jobs/${jid}/archive/info?format=${encodeURIComponent(st.format)}`).catch((e) => {
      gone = e.status === 404;
      return null;
    });
    if (info && info.format === st.format) st.info = info;
    if (gone) return this.loadJobs(); // deleted meanwhile: the job card says so, no link
    this.renderJobs();
  }

  async buildArchive(jid) {
    const st = this.archives.get(jid);
    st.busy = true;
    this.renderJobs();
    try {
      st.info = await api.post(`/jobs/${jid}/archive?format=${encodeURIComponent(st.format)}`);
    } catch (e) {
      showError(e);
      if (e.status === 404) st.info = null;
    } finally {
      st.busy = false;
      this.renderJobs();
    }
    if (!st.info) this.loadJobs();
  }

  async jobAction(j, action) {
    const r = await this.guard(() => api.post(`/jobs/${j.id}/${action}`));
    if (r) toast(`Job ${j.id}: ${action} requested.`);
    this.loadJobs();
  }

  /** Remember a started job so it shows at once; `then` runs when it finishes. */
  track(job, then = null) {
    this.jobs = [job, ...this.jobs.filter((j) => j.id !== job.id)];
    this.renderJobs();
    if (then) (this.onDone ||= new Map()).set(job.id, then);
  }

  async poll() {
    if (!this.alive) return;
    const active = this.jobs.filter((j) => ACTIVE.has(j.status));
    let finished = false;
    if (active.length) {
      const fresh = await Promise.all(active.map((j) => api.get(`/jobs/${j.id}`).catch(() => j)));
      for (const f of fresh) {
        const i = this.jobs.findIndex((j) => j.id === f.id);
        if (i >= 0) this.jobs[i] = f;
        if (!ACTIVE.has(f.status)) {
          const cb = this.onDone?.get(f.id);
          this.onDone?.delete(f.id);
          if (f.status === "failed") showError(`Job ${f.id} (${f.kind}) failed: ${f.message || "see its log"}`);
          else toast(`Job ${f.id} (${f.kind}) ${f.status}.`);
          if (cb) cb(f);
          finished = true;
          if (f.kind === "export") this.loadExportList();
          if (f.kind === "export" || f.kind === "eval") this.loadMetrics();
        }
      }
      if (this.alive) this.renderJobs();
    }
    // a finished job (import, selection, export, voxelize, ...) changes what the overview
    // and the scenes table count: frames to do, scenes, storage (issue 40: stale until reload)
    if (finished && this.alive) {
      this.loadOverview();
      this.loadScenes();
    }
    if (this.alive) this.timer = setTimeout(() => this.poll(), active.length ? 700 : 3000);
  }

  // ---- exports, metrics ------------------------------------------------------------------
  exportForm() {
    const layout = el("select", { id: "export-layout" }, ["occufly", "sscbench"].map((l) => el("option", { value: l }, l)));
    const go = el("button", { type: "submit", id: "start-export" }, "Start export");
    const vox = el("button", { type: "button", id: "start-voxelize" }, "Voxelize scene");
    vox.addEventListener("click", async () => {
      const job = await this.guard(() => api.post(`/scenes/${this.sid}/voxelize`));
      if (job) this.track(job);
    });
    const ev = el("button", { type: "button", id: "start-eval" }, "Run evaluation");
    ev.addEventListener("click", async () => {
      const job = await this.guard(() => api.post(`/scenes/${this.sid}/eval`));
      if (job) this.track(job);
    });
    // issue 23: accepted versions only by default; unreviewed ones (submitted, imported) by choice
    this.exportUnreviewed = el("input", { type: "checkbox", id: "export-include-unreviewed" });
    this.exportUnreviewed.addEventListener("change", () => this.loadExportPlan());
    const incl = el("label", { class: "check", for: "export-include-unreviewed", title: "Accepted masks only unless ticked: submitted and imported masks have not been reviewed" }, this.exportUnreviewed, " also take in unreviewed masks (submitted, imported)");
    const f = el("form", { class: "inline-form", "aria-label": "Export" }, field("Layout", layout), incl, go, vox, ev);
    f.addEventListener("submit", async (e) => {
      e.preventDefault();
      const include = this.exportInclude();
      const plan = await this.guard(() => api.get(`/scenes/${this.sid}/export/plan?include=${include.join(",")}`));
      if (!plan) return;
      this.showExportPlan(plan);
      if (!(await confirmExport(plan))) return;
      const job = await this.guard(() => api.post(`/scenes/${this.sid}/export`, { layout: layout.value, include }));
      if (job) {
        toast(`Export job ${job.id} started.`);
        this.track(job);
      }
    });
    return el("div", {}, f, this.exportPlanEl);
  }

  exportInclude() {
    return this.exportUnreviewed && this.exportUnreviewed.checked ? ["accepted", "submitted", "imported"] : ["accepted"];
  }

  /** Before an export: the draft and unreviewed frames, and what the export would take. */
  async loadExportPlan() {
    if (!this.sid) return;
    const plan = await api.get(`/scenes/${this.sid}/export/plan?include=${this.exportInclude().join(",")}`).catch(() => null);
    this.showExportPlan(plan);
  }

  showExportPlan(plan) {
    if (!plan) {
      this.exportPlanEl.replaceChildren();
      return;
    }
    const lo = plan.left_out || {};
    const drafts = lo.draft || [];
    const unrev = [...(lo.submitted || []), ...(lo.imported || [])].concat(plan.unreviewed_frames || []).sort((a, b) => a - b);
    const taken = plan.unreviewed_frames || [];
    this.exportPlanEl.replaceChildren(
      el("p", { class: "export-plan-took" }, `An export now takes ${plan.took}.`),
      el(
        "ul",
        { class: "export-plan-list" },
        el("li", { "data-kind": "draft" }, drafts.length ? `${drafts.length} frame${drafts.length === 1 ? "" : "s"} only in draft (never submitted): ${frameList(drafts)} — never exported.` : "No frame only in draft."),
        el("li", { "data-kind": "unreviewed" }, unrev.length ? `${unrev.length} frame${unrev.length === 1 ? "" : "s"} submitted or imported, not accepted: ${frameList(unrev)} — ${taken.length ? "taken in without review" : "left out"}.` : "Every voting mask is accepted."),
        (lo.rejected || []).length ? el("li", { "data-kind": "rejected" }, `${lo.rejected.length} rejected: ${frameList(lo.rejected)} — left out.`) : null,
      ),
    );
  }

  // ---- quality (issue 23) ----------------------------------------------------------------
  // ---- how the votes are decided (issue 37) ------------------------------------------------
  async loadLifting() {
    const sid = this.sid;
    if (!sid) return;
    clearTimeout(this.liftingTimer);
    const r = await this.guard(() => api.get(`/scenes/${sid}/lifting`));
    if (!r || sid !== this.sid || !this.alive) return; // another scene was chosen meanwhile
    this.liftingEl.replaceChildren(liftingView(r, (model, button) => this.applyLifting(sid, model, button)));
    // a fill with the new model is running: show its result when it is done
    if (r.status.pending_fill || r.status.pending_frames) this.liftingTimer = setTimeout(() => this.loadLifting(), 2000);
  }

  async applyLifting(sid, model, button) {
    button.disabled = true; // a double click applies once
    try {
      const r = await api.put(`/scenes/${sid}/lifting`, { model });
      const name = (this.scenes || []).find((s) => String(s.id) === String(sid))?.name || `scene ${sid}`;
      toast(`${name}: votes are now decided with “${LIFT_MODEL_NAMES[r.model]}”${r.status.pending_fill ? "; its labels are being filled again" : ""}.`);
      if (String(sid) === String(this.sid)) this.loadLifting();
      this.loadAudit();
    } catch (e) {
      showError(e);
      button.disabled = false;
    }
  }

  async loadQuality() {
    const sid = this.sid;
    if (!sid) return;
    clearTimeout(this.qualityTimer);
    let q = null;
    try {
      q = await api.get(`/scenes/${sid}/quality`);
    } catch (e) {
      if (e.status !== 404) showError(e);
      if (sid === this.sid) this.qualityEl.replaceChildren(el("p", {}, "No lifted labels yet: nothing to report."));
      return;
    }
    if (sid !== this.sid || !this.alive) return;
    // issue 38: the report is computed in the background (minutes on a survey): the page shows
    // the last one, says it is being brought up to date, and asks again until it is
    if (q && q.computing) this.qualityTimer = setTimeout(() => this.loadQuality(), 3000);
    if (q && q.computing && !q.loo && !q.votes) {
      this.qualityEl.replaceChildren(el("p", { class: "hint", "data-quality": "computing" }, "Computing the quality report (one leave-one-out decision per annotated frame) — it appears here when ready."));
      return;
    }
    const view = qualityView(q);
    if (q.stale) view.prepend(el("p", { class: "warn", "data-quality": "stale" }, "These figures are of earlier labels; the report of the current labels is being computed and replaces them when ready."));
    this.qualityEl.replaceChildren(view);
  }

  async loadMetrics() {
    let m = null;
    const evaluated = this.jobs.some((j) => j.kind === "eval" && j.status === "done" && String(j.scene_id ?? this.sid) === String(this.sid));
    if (!evaluated) {
      this.exportsEl.replaceChildren(el("h3", {}, "Metrics"), el("p", {}, "No evaluation results yet: press \u201cRun evaluation\u201d."));
      return;
    }
    try {
      m = await api.get(`/scenes/${this.sid}/metrics`);
    } catch (e) {
      if (e.status !== 404) showError(e);
    }
    this.exportsEl.replaceChildren(el("h3", {}, "Metrics"), m ? readableMetrics(m) : el("p", {}, "No evaluation results yet."));
  }

  async loadEffort() {
    let e = null;
    try {
      e = await api.get(`/scenes/${this.sid}/effort`);
    } catch (err) {
      this.effortEl.replaceChildren(el("p", {}, `No effort figures: ${err.message}`));
      return;
    }
    const rows = e.submissions || [];
    if (!rows.length) {
      this.effortEl.replaceChildren(el("p", {}, "No submitted masks yet."));
      return;
    }
    const t = e.totals;
    const c = el("canvas", { id: "effort-plot" });
    const pre = rows.filter((r) => r.prefilled).length;
    const summary = [
      `${t.submissions} submitted mask(s), ${pre} started from the 3D prefill. `,
      t.resubmissions ? `(${t.resubmissions} resubmission(s) of the same frames not counted again.) ` : "",
      `Painted from scratch: ${t.painted_px.toLocaleString()} px; changed versus the prefill: ${t.changed_px.toLocaleString()} px`,
      t.reduction_x != null ? ` (${t.reduction_x.toFixed(2)}\u00d7 less).` : ".",
      t.median_changed_of_painted_from_6th != null ? ` From the 6th submission on, the median mask changed ${pct(t.median_changed_of_painted_from_6th, 1)} of what painting it from scratch takes.` : "",
    ].join("");
    const last = rows.slice(-50).reverse();
    this.effortEl.replaceChildren(
      el("p", { id: "effort-summary" }, summary),
      c,
      el("details", {}, el("summary", {}, "Per submission (newest first, at most 50)"),
        table(last, [
          { key: "n", label: "#" },
          { key: "frame", label: "Frame" },
          { key: "author", label: "Annotator", fmt: (v) => v ?? "\u2013" },
          { key: "painted_share", label: "Painted", fmt: (v) => pct(v, 1) },
          { key: "changed_share", label: "Changed vs prefill", fmt: (v, r) => (r.prefilled ? pct(v, 1) : "no prefill") },
          { key: "created_at", label: "Submitted", fmt: (v) => fmtDate(v) },
        ])),
    );
    const x = (r) => r.n;
    linePlot(c, rows.map((r) => [x(r), r.changed_share]), {
      xLabel: "submission", yLabel: "% of the frame's pixels", xMin: 1, yMin: 0, yMax: 1, dots: true, width: 560, height: 280, xInteger: true,
      label: "changed vs prefill", yFmt: (v) => `${Math.round(v * 100)}%`,
      series: [{ points: rows.map((r) => [x(r), r.painted_share]), color: "#9e9e9e", dash: [5, 4], label: "painted from scratch", dots: true }],
    });
  }

  async loadHistogram() {
    try {
      const [st, scene] = await Promise.all([api.get(`/scenes/${this.sid}/labels/status`), api.get(`/scenes/${this.sid}`)]);
      const classes = (scene.taxonomy && scene.taxonomy.classes) || [];
      const hist = st.class_histogram || {};
      let bars = classes.map((c) => ({ label: c.name, value: Number(hist[c.id] ?? hist[String(c.id)] ?? 0), color: `rgb(${c.rgb.join(",")})` }));
      const extra = Object.keys(hist).filter((k) => !classes.some((c) => String(c.id) === k));
      for (const k of extra) bars.push({ label: k === "0" ? "unlabelled" : `id ${k}`, value: Number(hist[k]), color: "#999" });
      const zero = bars.filter((b) => !b.value).map((b) => b.label);
      bars = bars.filter((b) => b.value).sort((a, b) => b.value - a.value);
      const c = el("canvas", { id: "class-histogram" });
      const nv = Object.keys(st.included_versions || {}).length;
      // replaceChildren() turns a null argument into the text "null": pass only nodes
      this.histEl.replaceChildren(
        ...[
          el("p", {}, `Lifted labels include ${nv} mask version(s)${st.pending_fill ? "; kNN fill pending" : ""}. Points per class:`),
          bars.length ? c : el("p", {}, "No labelled points yet."),
          zero.length ? el("p", { class: "muted" }, `No points: ${zero.join(", ")}.`) : null,
        ].filter(Boolean),
      );
      if (bars.length) barPlot(c, bars, { title: "points per class", width: 560 });
    } catch (e) {
      this.histEl.replaceChildren(el("p", {}, `No label statistics: ${e.message}`));
    }
  }
}

const ISO = /^\d{4}-\d\d-\d\dT\d\d:\d\d/;
// shares (agreement, IoU, precision, recall, delta_k, coverage) show as percentages
const SHARE = /agreement|coverage|iou|precision|recall|delta|^d[123]$|accuracy/i;

/** One metric value as text; `dates`: ISO timestamps as local dates. */
// issue 37: the annotator models of the live lifting (the server's descriptions go beside them)
const LIFT_MODEL_NAMES = { pooled: "One model for all painters", per_author: "One model per painter" };
const LIFT_DECISIONS = { robust: "one model for all painters", confusion: "one model per painter", regions: "region consistency by painter", majority: "the plain vote majority" };

export function liftingView(r, apply) {
  const wrap = el("div", { "data-model": r.model, "data-scene": r.scene_id });
  const radios = r.models.map((m) => {
    const input = el("input", { type: "radio", name: "lift-model", id: `lift-model-${m.id}`, value: m.id });
    input.checked = m.id === r.model;
    return el("div", { class: "radio-row" }, input, el("label", { for: input.id }, el("strong", {}, LIFT_MODEL_NAMES[m.id] || m.id), m.id === r.model ? " (current)" : ""), el("small", { class: "hint" }, m.description));
  });
  const button = el("button", { type: "button", id: "lift-model-apply", disabled: true }, "Apply");
  const chosen = () => radios.map((d) => d.querySelector("input")).find((i) => i.checked)?.value;
  for (const d of radios) d.querySelector("input").addEventListener("change", () => { button.disabled = chosen() === r.model; });
  button.addEventListener("click", () => { const m = chosen(); if (m && m !== r.model) apply(m, button); });
  const fieldset = el("fieldset", { class: "lift-models" }, el("legend", {}, "Annotator model"), ...radios, button);
  const f = r.last_fill || {};
  const st = r.status || {};
  let last;
  if (!f.decision) last = "No fill yet: the labels are filled after the first mask is saved.";
  else {
    const p = f.painters;
    const who = p ? `, ${p.authors} painter${p.authors === 1 ? "" : "s"} told apart${p.frames_own ? ` (${p.frames_own} frame${p.frames_own === 1 ? "" : "s"} imported or without an author, each counted as a painter of its own)` : ""}` : "";
    const skipped = f.confusion_skipped ? ` (not applied: ${f.confusion_skipped})` : "";
    // a fill after a save keeps the model of the last full decision (issue 37, eighth round)
    const held = f.robust_warm ? ` It kept the model of the last full decision and decided again only the ${Number(f.robust_warm_decided || 0).toLocaleString("en")} points around the change; the model is fitted again once the scene is quiet.` : "";
    last = `Last fill: ${LIFT_DECISIONS[f.decision] || f.decision}${skipped}${who}; ${f.annotated_frames} painted frame${f.annotated_frames === 1 ? "" : "s"}${f.total_seconds != null ? `, ${Number(f.total_seconds).toFixed(1)} s` : ""}.${held}`;
  }
  const busy = st.pending_fill || st.pending_frames ? el("p", { class: "warn", id: "lift-pending" }, st.fill_running ? "A fill is running; its result appears here when it is done." : "A fill is due; its result appears here when it is done.") : null;
  // what the per-painter model learned: the true classes each painter paints as another
  const learned = (f.learned || []).length ? el("div", { id: "lift-learned" },
    el("p", {}, "What the model learned about the painters (a true class painted as another):"),
    el("ul", {}, ...f.learned.map((x) => el("li", { "data-painter": x.painter }, `${x.painter}: ` + x.confusions.map((c) => `${c.true} painted as ${c.painted} ${pct(c.share, 0)}${c.votes != null ? ` (of ~${c.votes.toLocaleString()} votes on ${c.true})` : ""}`).join("; "))))) : null;
  wrap.append(...[fieldset, el("p", { id: "lift-last" }, last), learned, busy, st.last_error ? el("p", { class: "error" }, `Last lifting error: ${st.last_error}`) : null].filter(Boolean));
  return wrap;
}

function formatMetric(v, key = "", { dates = false } = {}) {
  if (typeof v === "number") {
    if (SHARE.test(key) && v >= 0 && v <= 1) return `${(100 * v).toFixed(2)} %`;
    return Math.abs(v) <= 1 && !Number.isInteger(v) ? v.toFixed(4) : v.toLocaleString();
  }
  if (v === null || v === undefined) return "n/a";
  if (dates && typeof v === "string" && ISO.test(v)) return fmtDate(v);
  return typeof v === "object" ? JSON.stringify(v) : String(v);
}
// bookkeeping keys: identify the job or the row, not a measurement
const BOOKKEEPING = new Set(["job_id", "table", "frame_id", "index", "scene_id", "id", "finished_at", "created_at", "started_at"]);
const TABLE_TITLES = { agreement_2d: "2D agreement of the masks with the rendered 3D labels" };

function humanKey(k) {
  const special = { iou: "IoU", miou: "mIoU", n_frames: "frames", ssc: "SSC", per_class_iou: "IoU per class" };
  if (special[k]) return special[k];
  return String(k).replace(/^n_/, "").replace(/_/g, " ").replace(/\biou\b/gi, "IoU").replace(/\bmiou\b/gi, "mIoU");
}

/**
 * An eval result for people: a heading (which job, when), its tables without bookkeeping
 * columns, timestamps as local dates, shares as percentages; the raw values stay available
 * (collapsed) for whoever needs the exact keys.
 */
export function readableMetrics(m) {
  const fmt = (v, key = "") => formatMetric(v, key, { dates: true });
  const out = el("div", { class: "metrics readable", id: "metrics" });
  const when = m.finished_at ? ` · finished ${fmtDate(m.finished_at)}` : "";
  out.append(el("p", { class: "metrics-head" }, `Evaluation${m.job_id != null ? ` job #${m.job_id}` : ""}${when}`));
  const walk = (obj, title, depth) => {
    if (Array.isArray(obj) && obj.length && typeof obj[0] === "object") {
      const keys = [...new Set(obj.flatMap((r) => Object.keys(r)))].filter((k) => !BOOKKEEPING.has(k));
      out.append(table(obj, keys.map((k) => ({ key: k, label: humanKey(k), fmt: (v) => fmt(v, k) })), { caption: title }));
      return;
    }
    if (obj && typeof obj === "object" && !Array.isArray(obj)) {
      const heading = TABLE_TITLES[obj.table] || title;
      const scalars = Object.entries(obj).filter(([k, v]) => (v === null || typeof v !== "object") && !BOOKKEEPING.has(k));
      const unit = SHARE.test(title) ? title : "";
      if (scalars.length) {
        out.append(
          el(
            "dl",
            { class: "metric-list", "aria-label": heading || "metrics" },
            heading ? el("dt", { class: "metric-title" }, heading) : null,
            ...scalars.map(([k, v]) => el("div", { class: "metric" }, el("span", { class: "metric-name" }, humanKey(k)), el("strong", {}, fmt(v, unit || k)))),
          ),
        );
      }
      for (const [k, v] of Object.entries(obj)) if (v && typeof v === "object") walk(v, title && depth ? `${title} / ${humanKey(k)}` : humanKey(k), depth + 1);
      return;
    }
    if (obj !== undefined) out.append(el("p", {}, `${title}: ${fmt(obj, title)}`));
  };
  walk(m, "", 0);
  out.append(el("details", { class: "raw-metrics" }, el("summary", {}, "Raw values (as the API sends them)"), metricsView(m, "metrics-raw")));
  return out;
}

/** Render an eval result (nested dicts / lists of rows) as tables. */
export function metricsView(m, id = "metrics") {
  const out = el("div", { class: "metrics", id });
  const fmtv = (v, key = "") => formatMetric(v, key);
  const walk = (obj, title) => {
    // a table of shares keyed by class name (per_class_iou, ...) takes its unit from the title
    const fmt = (v, row) => fmtv(v, SHARE.test(title) ? title : row && row.k !== undefined ? row.k : "");
    if (Array.isArray(obj) && obj.length && typeof obj[0] === "object") {
      const cols = [...new Set(obj.flatMap((r) => Object.keys(r)))].map((k) => ({ key: k, label: k, fmt: (v) => fmtv(v, k) }));
      out.append(table(obj, cols, { caption: title }));
      return;
    }
    if (obj && typeof obj === "object" && !Array.isArray(obj)) {
      const scalars = Object.entries(obj).filter(([, v]) => v === null || typeof v !== "object");
      if (scalars.length) out.append(table(scalars.map(([k, v]) => ({ k, v })), [{ key: "k", label: "metric" }, { key: "v", label: "value", fmt }], { caption: title }));
      for (const [k, v] of Object.entries(obj)) if (v && typeof v === "object") walk(v, title ? `${title} / ${k}` : k);
      return;
    }
    out.append(el("p", {}, `${title}: ${fmtv(obj, title)}`));
  };
  walk(m, "");
  return out;
}

// ---- issue 23: export gating and the quality report ------------------------------------------
function frameList(ids, max = 12) {
  const shown = ids.slice(0, max).join(", ");
  return `frame${ids.length === 1 ? "" : "s"} ${shown}${ids.length > max ? `, … (${ids.length - max} more)` : ""}`;
}

/** Ask before an export that leaves frames out or takes unreviewed ones in; true = go. */
export async function confirmExport(plan) {
  const lo = plan.left_out || {};
  const left = Object.entries(lo).filter(([, v]) => v.length);
  const unrev = plan.unreviewed_frames || [];
  if (!(plan.taken || []).length && plan.labels_from_masks) {
    await dialog({
      title: "Nothing to export",
      body: el("div", { id: "export-nothing" }, el("p", {}, `No mask this export would take: ${plan.took}.`), el("p", {}, "Accept frames first, or tick \u201calso take in unreviewed masks\u201d.")),
      buttons: [{ label: "OK", value: false, primary: true }],
      cancelValue: false,
    });
    return false;
  }
  if (!left.length && !unrev.length) return true;
  const body = el(
    "div",
    { id: "export-confirm" },
    el("p", {}, `This export takes ${plan.took}.`),
    left.length
      ? el("p", {}, "Left out (their votes are not in the exported labels):", el("ul", {}, left.map(([k, v]) => el("li", { "data-left": k }, `${v.length} ${k === "draft" ? (v.length === 1 ? "draft" : "drafts") : k}: ${frameList(v)}`))))
      : null,
    unrev.length ? el("p", { class: "warn" }, `Taken in without review: ${frameList(unrev)}.`) : null,
    el("p", { class: "hint" }, "The manifest records every mask taken (version, state, author, reviewer); quality.json beside the data says how the labels were made."),
  );
  return dialog({ title: "Export these labels?", body, buttons: [{ label: "Cancel", value: false }, { label: "Export", value: true, primary: true }], cancelValue: false });
}

/** What a finished export took, on its job card: "done · 1685 files · 12 accepted frames; left out: 2 drafts". */
export function exportTook(j) {
  const r = j.result || {};
  if (j.kind !== "export" || j.status !== "done" || !r.review || !r.review.took) return null;
  const files = r.files ?? (r.summary && r.summary.frames);
  return el("span", { class: "export-took", "data-job": j.id }, `done · ${files ?? "?"} ${r.files !== undefined ? "files" : "frames"} · ${r.review.took}`);
}

export function qualityView(q) {
  const lo = q.loo || {};
  const d = lo.agreement_distribution || {};
  const qs = d.quantiles || {};
  const cf = q.confidence || {};
  const t = cf.truth;
  const rows = [
    { k: "Leave-one-out agreement", v: `${pct(lo.agreement)} of ${(lo.frames ?? 0).toLocaleString()} annotated frames' votes with independent labels`, id: "loo" },
    { k: "… per frame", v: d.n ? `min ${pct(qs.p0)} · p10 ${pct(qs.p10)} · median ${pct(qs.p50)} · max ${pct(qs.p100)}` : "–", id: "loo-frames" },
    { k: "Independent coverage", v: `${pct(lo.independent_coverage)} of the votes have labels from other frames`, id: "coverage" },
    { k: "Points with ≥ 2 views", v: `${pct(q.votes.multi_view_share)} of the labelled points`, id: "multi-view" },
    { k: "Contested points", v: `${pct(q.contested.share)} of the labelled points (votes disagree); ${pct(q.contested.overridden_share)} overridden by fill / denoise`, id: "contested" },
    { k: "Mean confidence", v: `${pct(cf.mean_confidence)} (the calibrated confidence's prediction of the share of right labels)`, id: "confidence" },
    { k: "Calibration", v: t ? `ECE ${t.ece.toFixed(4)} against point truth (${t.points.toLocaleString()} points, accuracy ${pct(t.accuracy)})` : "ECE not measured: no point truth for this scene", id: "ece" },
    { k: "Labelled points", v: `${q.labelled_points.toLocaleString()} of ${q.points.toLocaleString()} (${pct(q.labelled_share)})`, id: "labelled" },
    { k: "Version policy", v: (q.policy && q.policy.note) || ((q.policy && q.policy.include) || []).join(", "), id: "policy" },
  ];
  const hist = (d.histogram && d.histogram.counts) || [];
  const canvas = el("canvas", { id: "quality-loo-hist" });
  const bars = hist.map((c, i) => ({ label: `${i * 10}–${(i + 1) * 10} %`, value: c })).reverse();
  if (bars.length) barPlot(canvas, bars, { title: "annotated frames by leave-one-out agreement", valueFmt: (v) => `${v} frame${v === 1 ? "" : "s"}` });
  const worst = [...(lo.per_frame || [])].filter((r) => r.agreement !== null).sort((a, b) => a.agreement - b.agreement).slice(0, 5);
  const classes = Object.values(q.classes || {}).sort((a, b) => b.points - a.points);
  const painters = q.painters || []; // issue 37: the API adds who painted what
  return el(
    "div",
    { class: "quality", "data-stamp": q.labels_stamp || "" },
    table(rows, [{ key: "k", label: "Figure" }, { key: "v", label: "Value" }], { caption: "Quality of the live labels", rowAttrs: (r) => ({ "data-figure": r.id }) }),
    el("div", { class: "plots" },
      el("figure", {}, canvas, el("figcaption", {}, "Annotated frames by leave-one-out agreement (a wrong mask scores low)")),
      worst.length ? el("figure", {}, table(worst, [{ key: "name", label: "Lowest frames" }, { key: "agreement", label: "LOO agreement", fmt: (v) => pct(v) }, { key: "independent_coverage", label: "Independent coverage", fmt: (v) => pct(v) }]), el("figcaption", {}, "Review these first")) : null,
    ),
    painters.length ? table(painters, [
      { key: "painter", label: "Painter" },
      { key: "frames", label: "Frames" },
      { key: "agreement", label: "LOO agreement", fmt: (v) => pct(v) },
      { key: "independent", label: "Votes with an independent label", fmt: (v) => v.toLocaleString() },
      { key: "disagreements", label: "Most frequent disagreements (painted → others say)", fmt: (v) => (v && v.length ? v.map((d) => `${d.painted} → ${d.independent} (${d.votes.toLocaleString()})`).join("; ") : "–") },
    ], { caption: "Per painter: a painter far below the others who swaps the same pair on every frame is outvoted by “One model per painter” (Lifting section)", rowAttrs: (r) => ({ "data-painter": r.painter }) }) : null,
    table(classes, [
      { key: "name", label: "Class" },
      { key: "points", label: "Points", fmt: (v) => v.toLocaleString() },
      { key: "mean_confidence", label: "Mean confidence", fmt: (v) => pct(v) },
      { key: "multi_view", label: "≥ 2 views", fmt: (v) => pct(v) },
      { key: "contested", label: "Contested", fmt: (v) => pct(v) },
      { key: "loo_agreement", label: "LOO agreement", fmt: (v) => pct(v) },
      ...(t ? [{ key: "accuracy", label: "Accuracy (truth)", fmt: (v) => pct(v) }] : []),
    ], { caption: "Per class", rowAttrs: (r) => ({ "data-class": r.name }) }),
  );
}
