// Admin console pieces of issue 28 (used by admin.js): the folder browser confined to the
// import roots, the zip upload of a project folder, members at import, the users table
// (role, deactivate, reset password), storage and deletion with what it frees, exports
// with their bytes, the overview across scenes and annotators.

import { api } from "../core/api.js";
import { el, showError, toast, fmtDate, table, dialog } from "../core/ui.js";

// the styles of these pieces, loaded once with the module (style-src 'self')
if (!document.querySelector("link[data-console-css]")) document.head.append(el("link", { rel: "stylesheet", href: "/css/console.css", "data-console-css": "" }));

/** Bytes as text: 1.93 GB, 12.4 MB, 830 kB, 512 B. */
export function bytes(b) {
  if (b == null) return "–";
  if (b >= 1e9) return `${(b / 1e9).toFixed(2)} GB`;
  if (b >= 1e6) return `${(b / 1e6).toFixed(1)} MB`;
  if (b >= 1e3) return `${(b / 1e3).toFixed(0)} kB`;
  return `${b} B`;
}

/** Seconds as "2 h 05 min" / "7 min" / "40 s". */
export function duration(s) {
  if (s == null) return "–";
  if (s < 60) return `${Math.round(s)} s`;
  const m = Math.round(s / 60);
  return m < 60 ? `${m} min` : `${Math.floor(m / 60)} h ${String(m % 60).padStart(2, "0")} min`;
}

async function guard(fn) {
  try {
    return await fn();
  } catch (e) {
    showError(e);
    return null;
  }
}

// ---- folder browser ------------------------------------------------------------------------
/**
 * A modal listing the folders (and files) under the server's import roots; resolves with the
 * chosen path or null. `pick`: "dir" (choose the open folder), "file" (click a file) or
 * "any" (either: a Metashape project is its cameras .xml, other projects a folder).
 */
export async function browseFolder({ start = "", pick = "dir", title = "Choose a folder on the server" } = {}) {
  return new Promise((resolve) => {
    const d = el("dialog", { class: "modal folder-browser", id: "folder-browser", "aria-labelledby": "fb-title" });
    const where = el("p", { class: "fb-path", id: "fb-path" });
    const list = el("ul", { class: "fb-list", id: "fb-list" });
    const msg = el("p", { class: "muted", "aria-live": "polite" });
    let current = null;
    const done = (v) => {
      d.close();
      d.remove();
      resolve(v);
    };
    const choose = el("button", { type: "button", class: "primary", id: "fb-choose", disabled: true, onclick: () => done(current) }, "Choose this folder");
    const open = async (path) => {
      msg.textContent = "";
      let r;
      try {
        r = await api.get(`/imports/browse${path ? `?path=${encodeURIComponent(path)}` : ""}`);
      } catch (e) {
        msg.textContent = e.message;
        if (path) return open("");
        return;
      }
      current = r.path;
      choose.disabled = !current || pick === "file";
      where.replaceChildren(current ? el("code", {}, current) : el("span", {}, `Import roots: ${r.roots.join(", ")}`));
      const rows = [];
      if (current) rows.push(el("li", {}, el("button", { type: "button", class: "link fb-up", onclick: () => open(r.parent || "") }, r.parent ? "\u2191 parent folder" : "\u2191 import roots")));
      for (const e of r.entries) {
        if (e.kind === "dir") {
          rows.push(el("li", { "data-kind": "dir" }, el("button", { type: "button", class: "link fb-dir", "data-path": e.path, onclick: () => open(e.path) }, `${e.name}/`), e.exists === false ? el("span", { class: "muted" }, " (not created yet)") : null));
        } else if (e.hard_link) {  // an import refuses it: shown, not offered
          rows.push(el("li", { "data-kind": "file", "data-refused": "hard-link" }, el("span", { class: "muted" }, e.name),
            el("span", { class: "warn fb-refused" }, ` \u26a0 ${e.refused}`)));
        } else {
          rows.push(el("li", { "data-kind": "file" }, pick !== "dir"
            ? el("button", { type: "button", class: "link fb-file", "data-path": e.path, onclick: () => done(e.path) }, e.name)
            : el("span", { class: "muted" }, e.name), el("span", { class: "muted" }, ` ${bytes(e.bytes)}`)));
        }
      }
      if (!r.entries.length) rows.push(el("li", { class: "muted" }, "(empty)"));
      if (r.truncated) rows.push(el("li", { class: "muted" }, "\u2026 more entries are not shown"));
      list.replaceChildren(...rows);
    };
    d.append(
      el("h2", { id: "fb-title" }, title),
      el("p", { class: "hint" }, "Only folders inside the server's allowed import roots (and uploaded projects) are shown."),
      where, list, msg,
      el("div", { class: "dlg-buttons" }, choose, el("button", { type: "button", onclick: () => done(null) }, "Cancel")),
    );
    d.addEventListener("cancel", (e) => {
      e.preventDefault();
      done(null);
    });
    document.body.append(d);
    d.showModal();
    open(start);
  });
}

/** An input with a "Browse…" button that fills it from the folder browser. */
export function withBrowse(input, { pick = "dir", title } = {}) {
  const b = el("button", { type: "button", class: "small browse", "aria-label": `Browse for ${input.id}`, onclick: async () => {
    const start = input.value.trim();
    const p = await browseFolder({ start: start.startsWith("/") ? start : "", pick, title });
    if (p) {
      input.value = p;
      input.dispatchEvent(new Event("input"));
    }
  } }, "Browse\u2026");
  return el("span", { class: "with-browse" }, input, b);
}

/** Upload a zip of a project folder; `onDone(result)` gets {source, path, files, bytes}. */
export function uploadControls(nameInput, onDone) {
  const file = el("input", { type: "file", id: "imp-zip", accept: ".zip,application/zip", "aria-label": "Zip of a project folder" });
  const status = el("span", { class: "muted", id: "imp-zip-status", "aria-live": "polite" });
  const go = el("button", { type: "button", id: "imp-upload", onclick: async () => {
    const f = file.files && file.files[0];
    if (!f) {
      showError("Choose a .zip of the project folder first.");
      return;
    }
    const name = (nameInput.value.trim() || f.name.replace(/\.zip$/i, "")).replace(/[^A-Za-z0-9_.-]/g, "_").replace(/^[.-]+/, "");
    status.textContent = `Uploading ${f.name} (${bytes(f.size)})\u2026`;
    const r = await guard(async () => {
      const res = await api.send("POST", `/imports/upload?name=${encodeURIComponent(name)}`, { body: f, headers: { "Content-Type": "application/zip" } });
      return res.json();
    });
    status.textContent = r ? `Uploaded: ${r.files} files, ${bytes(r.bytes)} in ${r.source}` : "";
    if (r) onDone(r);
  } }, "Upload zip");
  return el("div", { class: "field upload" }, el("label", { for: "imp-zip" }, "Or upload a project"), el("span", { class: "with-browse" }, file, go), el("small", {}, "a .zip of the project folder; it is unpacked on the server and its folder filled in above"), status);
}

/** Checkboxes of the annotators and reviewers a new scene gets as members. */
export function memberPicker(users) {
  const box = el("fieldset", { class: "member-picker", id: "imp-members" }, el("legend", {}, "Members (who sees the scene)"));
  const people = (users || []).filter((u) => u.role !== "admin" && u.active !== false);
  if (!people.length) box.append(el("p", { class: "hint" }, "No annotators or reviewers yet: create them under Users."));
  for (const u of people) {
    const id = `imp-member-${u.id}`;
    box.append(el("label", { class: "check", for: id }, el("input", { type: "checkbox", id, value: u.id, "data-username": u.username }), ` ${u.username} `, el("span", { class: `role role-${u.role}` }, u.role)));
  }
  box.selected = () => [...box.querySelectorAll("input:checked")].map((i) => Number(i.value));
  return box;
}

// ---- users ---------------------------------------------------------------------------------
/** The users table with role, active and password actions; `reload()` after a change. */
export function usersTable(users, me, reload) {
  const roleSel = (u) => {
    const s = el("select", { "aria-label": `Role of ${u.username}`, class: "user-role", disabled: me && u.id === me.id }, ["annotator", "reviewer", "admin"].map((r) => el("option", { value: r }, r)));
    s.value = u.role;
    s.addEventListener("change", async () => {
      const r = await guard(() => api.patch(`/users/${u.id}`, { role: s.value }));
      if (r) toast(`${u.username} is now ${r.role}.`);
      reload();
    });
    return s;
  };
  const actions = (u) =>
    el(
      "span",
      { class: "row-actions" },
      el("button", { type: "button", class: `small ${u.active ? "" : "primary"} user-active`, disabled: me && u.id === me.id, onclick: async () => {
        if (u.active) {
          const ok = await dialog({ title: `Deactivate ${u.username}?`, body: el("p", {}, `${u.username} is logged out everywhere and cannot log in until reactivated. Their masks and history stay.`), buttons: [{ label: "Deactivate", value: true, primary: true }, { label: "Cancel", value: false }] });
          if (!ok) return;
        }
        const r = await guard(() => api.patch(`/users/${u.id}`, { active: !u.active }));
        if (r) toast(`${u.username} ${r.active ? "reactivated" : "deactivated"}.`);
        reload();
      } }, u.active ? "Deactivate" : "Reactivate"),
      el("button", { type: "button", class: "small user-reset", onclick: async () => {
        const pw = el("input", { type: "password", id: "reset-password", minlength: 8, autocomplete: "new-password", "aria-label": "New password" });
        const ok = await dialog({ title: `New password for ${u.username}`, body: el("div", {}, el("p", {}, "At least 8 characters. Every session of this user ends."), pw), buttons: [{ label: "Set password", value: true, primary: true }, { label: "Cancel", value: false }] });
        if (!ok) return;
        const r = await guard(() => api.post(`/users/${u.id}/password`, { password: pw.value }));
        if (r) toast(`Password of ${u.username} reset; ${r.count} session(s) ended.`);
      } }, "Reset password"),
    );
  return table(users, [
    { key: "username", label: "User" },
    { key: "role", label: "Role", fmt: (_v, u) => roleSel(u) },
    { key: "active", label: "Status", fmt: (v) => el("span", { class: v ? "ok" : "muted" }, v ? "active" : "deactivated") },
    { key: "created_at", label: "Created", fmt: fmtDate },
    { key: "id", label: "", fmt: (_v, u) => actions(u) },
  ], { rowAttrs: (u) => ({ "data-user": u.username, "data-active": String(u.active) }) });
}

// ---- storage and deletion ----------------------------------------------------------------------
/** Confirm deleting a scene: what it frees, typed name; resolves true when deleted. */
export async function confirmDeleteScene(scene) {
  const p = await guard(() => api.get(`/scenes/${scene.id}/deletion`));
  if (!p) return false;
  const typed = el("input", { id: "confirm-scene-name", autocomplete: "off", "aria-label": "Scene name" });
  const body = el(
    "div",
    { id: "delete-scene-preview" },
    el("p", {}, `Deleting ${scene.name} frees `, el("strong", { id: "delete-frees" }, bytes(p.freed_bytes)), ":"),
    el("ul", {},
      el("li", {}, `workspace ${bytes(p.workspace_bytes)} (${p.frames} frames)`),
      el("li", {}, `${p.exports} export(s) ${bytes(p.export_bytes)}`),
      el("li", {}, `${p.mask_versions} mask version(s), ${bytes(p.mask_bytes)} of mask files no other scene uses`),
      el("li", {}, `cached images ${bytes(p.cache_bytes)}`)),
    el("p", { class: "muted" }, `The import source ${p.source_kept || ""} is kept.`),
    p.blocked_by.length ? el("p", { class: "notice" }, `Not possible now: ${p.blocked_by.join("; ")}`) : null,
    el("label", { for: "confirm-scene-name" }, `Type ${scene.name} to confirm`), typed,
  );
  const ok = await dialog({ title: `Delete scene ${scene.name}?`, body, buttons: [{ label: `Delete and free ${bytes(p.freed_bytes)}`, value: true, primary: true }, { label: "Cancel", value: false }] });
  if (!ok) return false;
  const r = await guard(async () => (await api.send("DELETE", `/scenes/${scene.id}?confirm=${encodeURIComponent(typed.value)}`)).json());
  if (r) toast(`Scene ${scene.name} deleted; ${bytes(r.freed_bytes)} freed.`);
  return !!r;
}

/** Confirm deleting an export (row of GET /exports); resolves true when deleted. */
export async function confirmDeleteExport(x) {
  const ok = await dialog({
    title: `Delete export job ${x.job_id}?`,
    body: el("p", { id: "delete-export-preview" }, `The ${x.layout || ""} export of ${x.scene || "scene " + x.scene_id} finished ${fmtDate(x.finished_at)}: deleting it frees `, el("strong", {}, bytes(x.bytes)), ` (output ${bytes(x.output_bytes)}, archives ${bytes(x.archive_bytes)}).`),
    buttons: [{ label: `Delete and free ${bytes(x.bytes)}`, value: true, primary: true }, { label: "Cancel", value: false }],
  });
  if (!ok) return false;
  const r = await guard(async () => (await api.send("DELETE", `/jobs/${x.job_id}/export`)).json());
  if (r) toast(`Export job ${x.job_id} deleted; ${bytes(r.freed_bytes)} freed.`);
  return !!r;
}

/** The exports table with sizes and Delete buttons. */
export function exportsTable(rows, reload) {
  const live = rows.filter((x) => !x.deleted_at);
  if (!live.length) return el("p", { class: "hint" }, "No exports on disk.");
  return table(live, [
    { key: "job_id", label: "Job" },
    { key: "scene", label: "Scene", fmt: (v, x) => v ?? `scene ${x.scene_id}` },
    { key: "layout", label: "Layout" },
    { key: "finished_at", label: "Finished", fmt: fmtDate },
    { key: "bytes", label: "On disk", fmt: (v) => bytes(v) },
    { key: "job_id", label: "", fmt: (_v, x) => el("button", { type: "button", class: "small danger export-delete", "aria-label": `Delete export job ${x.job_id}`, onclick: async () => { if (await confirmDeleteExport(x)) reload(); } }, "Delete") },
  ], { caption: `${live.length} export(s), ${bytes(live.reduce((a, x) => a + x.bytes, 0))}`, rowAttrs: (x) => ({ "data-export": x.job_id }) });
}

// ---- overview ------------------------------------------------------------------------------
export function overviewView(o) {
  if (!o.scenes.length) return el("p", { class: "hint" }, "No scenes yet.");
  const n = (v) => (v == null ? "–" : String(v));
  const lag = (s) => (s.lift_pending_frames ? `${duration(s.lift_lag_s)} (${s.lift_pending_frames} waiting)` : "none");
  const perHour = (v) => (v == null ? "–" : `${v.toFixed(1)}/h`);
  const scenes = table(o.scenes, [
    { key: "scene", label: "Scene" },
    { key: "todo", label: "To do", fmt: n },
    { key: "in_progress", label: "In progress", fmt: n },
    { key: "submitted", label: "Submitted", fmt: n },
    { key: "accepted", label: "Accepted", fmt: n },
    { key: "rejected", label: "Rejected", fmt: n },
    { key: "submissions", label: "Submissions", fmt: n },
    { key: "time_spent_s", label: "Time spent", fmt: duration },
    { key: "frames_per_hour", label: "Throughput", fmt: perHour },
    { key: "lift_lag_s", label: "Lifting lag", fmt: (_v, s) => lag(s) },
  ], { caption: "Per scene (selected frames)", rowAttrs: (s) => ({ "data-scene": s.scene }) });
  const people = o.scenes.flatMap((s) => s.annotators.map((a) => ({ ...a, scene: s.scene })));
  const perPerson = people.length
    ? table(people, [
        { key: "username", label: "Annotator" },
        { key: "scene", label: "Scene" },
        { key: "in_progress", label: "In progress", fmt: n },
        { key: "submitted", label: "Submitted", fmt: n },
        { key: "accepted", label: "Accepted", fmt: n },
        { key: "rejected", label: "Rejected", fmt: n },
        { key: "submissions", label: "Submissions", fmt: (v, a) => (a.resubmissions ? `${v} (${a.resubmissions} again)` : n(v)) },
        { key: "time_spent_s", label: "Time spent", fmt: duration },
        { key: "frames_per_hour", label: "Throughput", fmt: perHour },
        { key: "last_active_at", label: "Last active", fmt: fmtDate },
      ], { caption: "Per annotator and scene", rowAttrs: (a) => ({ "data-annotator": a.username, "data-scene": a.scene }) })
    : el("p", { class: "hint" }, "Nobody has worked on a frame yet.");
  const total = o.annotators.length
    ? table(o.annotators, [
        { key: "username", label: "Annotator" },
        { key: "role", label: "Role" },
        { key: "scenes", label: "Scenes", fmt: n },
        { key: "in_progress", label: "In progress", fmt: n },
        { key: "submitted", label: "Submitted", fmt: n },
        { key: "accepted", label: "Accepted", fmt: n },
        { key: "rejected", label: "Rejected", fmt: n },
        { key: "time_spent_s", label: "Time spent", fmt: duration },
        { key: "frames_per_hour", label: "Throughput", fmt: perHour },
      ], { caption: "Per annotator, all scenes", rowAttrs: (a) => ({ "data-annotator-total": a.username }) })
    : null;
  return el("div", { class: "overview" }, scenes, perPerson, total,
    el("p", { class: "muted" }, `Time spent: mask saves of one person less than ${Math.round(o.idle_gap_s / 60)} minutes apart, summed; throughput: frames submitted per hour of it (from a minute of recorded work on).`));
}

/** A labelled path input with its "Browse…" button (the folder browser above). */
export function pathField(label, input, hint = null, opts = {}) {
  return el("div", { class: "field" }, el("label", { for: input.id }, label), withBrowse(input, opts), hint ? el("small", {}, hint) : null);
}
