// The server the tests talk to: BLENDSPLAT_URL and BLENDSPLAT_API_KEY when set, else `blendsplat up` from the
// repository's venv on free ports with a temporary data dir (stopped after the tests).
import { spawn } from "node:child_process";
import { mkdtempSync, readFileSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { dirname, join, resolve } from "node:path";
import { fileURLToPath } from "node:url";

const ROOT = resolve(dirname(fileURLToPath(import.meta.url)), "..", "..", "..", "..");

export async function startServer() {
  if (process.env.BLENDSPLAT_URL && process.env.BLENDSPLAT_API_KEY) {
    return { url: process.env.BLENDSPLAT_URL, key: process.env.BLENDSPLAT_API_KEY, stop: async () => {} };
  }
  const dir = mkdtempSync(join(tmpdir(), "blendsplat-js-"));
  const env = Object.fromEntries(Object.entries(process.env).filter(([k]) => !k.startsWith("BLENDSPLAT_")));
  const proc = spawn(join(ROOT, ".venv", "bin", "blendsplat"),
    ["up", "--grpc-port", "0", "--http-port", "0", "--data-dir", join(dir, "data")],
    { env: { ...env, BLENDSPLAT_WARMUP_SIZE: "32", BLENDSPLAT_DRAIN_SECONDS: "1", PYTHONUNBUFFERED: "1" },
      stdio: ["ignore", "pipe", "pipe"] });
  let log = "";
  const port = await new Promise((done, fail) => {
    const timer = setTimeout(() => fail(new Error(`blendsplat up not ready in 180 s:\n${log.slice(-2000)}`)), 180000);
    const read = (chunk) => {
      log += chunk;
      const m = /ready: gRPC on port (\d+), HTTP on port (\d+)/.exec(log);
      if (m) { clearTimeout(timer); done(Number(m[2])); }
    };
    proc.stdout.on("data", read);
    proc.stderr.on("data", read);
    proc.on("exit", (code) => { clearTimeout(timer); fail(new Error(`blendsplat up exited ${code}:\n${log.slice(-2000)}`)); });
  });
  const stop = async () => {
    const exited = new Promise((done) => proc.once("exit", done));
    proc.kill("SIGTERM");
    const timer = setTimeout(() => proc.kill("SIGKILL"), 30000);
    await exited;
    clearTimeout(timer);
    rmSync(dir, { recursive: true, force: true });
  };
  return { url: `http://127.0.0.1:${port}`, key: readFileSync(join(dir, "data", "admin.key"), "utf8").trim(), stop };
}

export const DATA = join(ROOT, "clients", "python", "examples", "data");
